// One sequence from dataset to results, as `flatslam run --out DIR` and each sequence of
// `flatslam batch` write it: stats.csv and trajectory.tum streamed while frames are tracked, the
// refined trajectories, the ground truth, the sequence's row of the results table and its report.
// Concurrency: RunRecorder is used by one thread at a time (the track stage, then the caller);
// RunSequence blocks its caller like RunSlam, and several may run at once on distinct folders.
#pragma once

#include <array>
#include <atomic>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "io/manifest.h"
#include "jobs/slam_runner.h"
#include "report/results.h"
#include "storage/line_log.h"

namespace flatslam {

// This process's memory: peak and current resident set, and the heap the allocator has committed
// now (without code, stacks and mapped files). MiB; 0 where the system does not say.
[[nodiscard]] double PeakRssMiB();
[[nodiscard]] double CurrentRssMiB();
[[nodiscard]] double HeapCommittedMiB();

// Per-frame times of a session of any length in fixed memory: log-spaced bins 1% apart from
// 1 us to 100 s give the median within 1%; mean and maximum are exact.
class TimeStats {
 public:
  void Add(double ms);
  [[nodiscard]] double Median() const;
  [[nodiscard]] double Mean() const { return count_ == 0 ? 0 : sum_ / static_cast<double>(count_); }
  [[nodiscard]] double Max() const { return max_; }
  [[nodiscard]] double Sum() const { return sum_; }

 private:
  static constexpr double kMinMs = 1e-3, kMaxMs = 1e5, kStep = 1.01;
  std::array<uint32_t, 1900> bins_{};  // log(1e8) / log(1.01) = 1852 bins
  size_t count_ = 0;
  double sum_ = 0, max_ = 0;
};

// What a run writes while frames are tracked, and its counts. With an output folder: stats.csv
// (one line per frame: state, features, matches, times, resident set, heap, map size) and
// trajectory.tum (poses as tracked), whole lines flushed at least every second, so a killed run
// leaves both readable.
class RunRecorder {
 public:
  struct Counts {
    // lost: frames without a pose once the run had its first: lost and relocalizing, and a
    // monocular run's frames between a loss and its new segment's two-view start.
    // not_initialized: frames before the first pose only.
    size_t frames = 0, keyframes = 0, lost = 0, not_initialized = 0, relocalized = 0, reinitialized = 0;
    size_t lost_stretches = 0;  // runs of consecutive lost frames
    TimeStats track_ms, extract_ms;
    // Per stretch of lost frames after a frame this run tracked, that frame's inliers.
    std::vector<int> inliers_before_loss;
    // Times of the frames at which a new map segment started (FrameReport::reinitialized).
    std::vector<int64_t> new_segment_t_ns;
  };
  // out_dir empty: counts only. resumed_frames: the trajectory of the session a resumed run
  // continues (its stats.csv lines before first_frame are kept, its poses start trajectory.tum).
  explicit RunRecorder(const std::optional<std::filesystem::path>& out_dir, size_t first_frame = 0,
                       const std::vector<AnchoredFramePose>* resumed_frames = nullptr);
  // For SlamRunOptions::on_frame.
  void OnFrame(const FrameReport& report);
  // For SlamRunOptions::before_checkpoint: every line so far to the OS.
  void Flush();
  // Closes the streams and replaces the poses as tracked by the refined ones: trajectory.tum,
  // trajectory.kitti, keyframes.tum (each atomically), when the run tracked any frame.
  void Finish(const SlamRunResult& result);
  [[nodiscard]] const Counts& counts() const { return counts_; }

 private:
  std::optional<std::filesystem::path> out_dir_;
  std::optional<LineLog> csv_, poses_;
  Counts counts_;
  bool started_ = false;   // a frame had a pose (a resumed run starts with the poses it continues)
  bool losing_ = false;    // the last frame given to tracking was lost
  int last_inliers_ = -1;  // of the last frame tracked (-1: none tracked by this run)
};

// The row of the results table for a finished run (no ground-truth metrics yet).
[[nodiscard]] SequenceResult ResultOfRun(const SlamRunResult& run, const RunRecorder::Counts& counts);

// Fills the ground-truth metrics of `result`: ATE after SE(3) and Sim(3), scale, RPE per frame,
// the path length over the time the estimate covers, and the KITTI metric when the path is long
// enough. An estimate that does not overlap the ground truth leaves them empty.
void ScoreAgainstGroundTruth(const Trajectory& ground_truth, const Trajectory& estimate, SequenceResult* result);

// Writes what a sequence's folder holds besides the run's own files: groundtruth.tum (when
// there is ground truth), results.csv (the one row) and report.html.
void WriteSequenceSummary(const std::filesystem::path& out_dir, const SequenceResult& result,
                          const std::optional<Trajectory>& ground_truth);

struct SequenceRunOptions {
  const Vocabulary* vocabulary = nullptr;   // shared by every sequence; null: no place recognition
  bool deterministic = false;               // SlamRunOptions::deterministic
  std::filesystem::path out_dir;            // the sequence's folder (created)
  size_t input = 0;                         // SequenceResult::input
  const std::atomic<bool>* stop = nullptr;  // SlamRunOptions::stop
  // Called once the dataset is open with the number of frames to run, then from the track stage
  // after every frame. Either may be empty.
  std::function<void(size_t frames)> on_opened;
  std::function<void(const FrameReport&)> on_frame;
  std::function<void(const std::string&)> on_warning;  // skipped frames and failed background work
  // The peak resident set to report for the sequence (MiB); empty: the process's peak so far.
  // A batch running several sequences at once gives the peak it saw while this one ran.
  std::function<double()> peak_rss_mib;
};

// Opens spec.dataset, applies its settings and options, runs SLAM and writes the folder. A
// failure of the sequence itself (unreadable dataset, bad option, failed run) does not throw: the
// result says "failed" with the error, and whatever was computed is written.
[[nodiscard]] SequenceResult RunSequence(const SequenceSpec& spec, const SequenceRunOptions& options);

}  // namespace flatslam
