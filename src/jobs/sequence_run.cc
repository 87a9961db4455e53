#include "jobs/sequence_run.h"

#include <mimalloc.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <charconv>
#include <cmath>
#include <fstream>

#include "core/atomic_write.h"
#include "core/clock.h"
#include "core/error.h"
#include "io/dataset.h"
#include "io/orb_settings.h"
#include "jobs/map_camera.h"
#include "report/html_report.h"
#include "config/slam_config.h"
#include "trajectory/metrics.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {

double PeakRssMiB() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

double CurrentRssMiB() {
  std::ifstream statm("/proc/self/statm");
  double size = 0, resident = 0;
  if (!(statm >> size >> resident)) return 0;
  return resident * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

double HeapCommittedMiB() {
  size_t elapsed = 0, user = 0, system = 0, rss = 0, peak_rss = 0, commit = 0, peak_commit = 0, faults = 0;
  mi_process_info(&elapsed, &user, &system, &rss, &peak_rss, &commit, &peak_commit, &faults);
  return static_cast<double>(commit) / (1024.0 * 1024.0);
}

void TimeStats::Add(double ms) {
  const double clamped = std::clamp(ms, kMinMs, kMaxMs);
  ++bins_[static_cast<size_t>(std::log(clamped / kMinMs) / std::log(kStep))];
  ++count_;
  sum_ += ms;
  max_ = std::max(max_, ms);
}

double TimeStats::Median() const {
  size_t seen = 0;
  for (size_t b = 0; b < bins_.size(); ++b) {
    seen += bins_[b];
    if (2 * seen > count_) return kMinMs * std::pow(kStep, static_cast<double>(b) + 0.5);
  }
  return 0;
}

namespace {

constexpr const char* kStatsHeader =
    "frame,t_ns,state,keyframe,reinitialized,relocalized,features,stereo_points,matches,inliers,extract_ms,"
    "track_ms,rss_mib,heap_mib,map_keyframes,map_points\n";

// stats.csv lines of frames before `next_frame` (a resumed run keeps the first part's lines).
std::string StatsBefore(const std::filesystem::path& path, size_t next_frame) {
  std::ifstream in(path);
  std::string out = kStatsHeader, line;
  if (!in) return out;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    if (in.eof()) break;  // a last line without its newline is incomplete
    size_t frame = 0;
    const auto [ptr, ec] = std::from_chars(line.data(), line.data() + line.size(), frame);
    if (ec != std::errc() || *ptr != ',' || frame >= next_frame) continue;
    out += line + "\n";
  }
  return out;
}

}  // namespace

RunRecorder::RunRecorder(const std::optional<std::filesystem::path>& out_dir, size_t first_frame,
                         const std::vector<AnchoredFramePose>* resumed_frames)
    : out_dir_(out_dir), started_(resumed_frames && !resumed_frames->empty()) {
  if (!out_dir_) return;
  const std::filesystem::path csv_path = *out_dir_ / "stats.csv";
  if (resumed_frames) {
    const std::string kept = StatsBefore(csv_path, first_frame);
    WriteFileAtomically(csv_path, [&](std::FILE* f) { std::fputs(kept.c_str(), f); });
    csv_.emplace(csv_path, "", LineLog::Mode::kAppend);
  } else {
    csv_.emplace(csv_path, kStatsHeader);
  }
  std::string prefix = kTumHeader;
  if (resumed_frames)
    for (const AnchoredFramePose& f : *resumed_frames)
      prefix += FormatTumLine({f.t_ns, f.T_cam_world.isometry().inverse()});
  poses_.emplace(*out_dir_ / "trajectory.tum", prefix);
}

void RunRecorder::OnFrame(const FrameReport& r) {
  ++counts_.frames;
  if (!r.skipped) {
    counts_.keyframes += r.keyframe;
    const bool waiting = r.state == TrackingState::kNotInitialized;
    const bool lost = r.state == TrackingState::kLost || (waiting && started_);
    counts_.lost += lost;
    counts_.not_initialized += waiting && !started_;
    if (lost && !losing_) {
      ++counts_.lost_stretches;
      if (last_inliers_ >= 0) counts_.inliers_before_loss.push_back(last_inliers_);
    }
    losing_ = lost;
    if (r.T_world_cam) {
      started_ = true;
      last_inliers_ = r.inliers;
    }
    counts_.relocalized += r.relocalized;
    counts_.reinitialized += r.reinitialized;
    if (r.reinitialized) counts_.new_segment_t_ns.push_back(r.t_ns);
    counts_.track_ms.Add(r.track_ms);
    counts_.extract_ms.Add(r.extract_ms);
  }
  // Resident set and committed heap sampled every frame: long sessions show whether memory stays
  // flat.
  if (csv_) {
    char line[512];
    std::snprintf(line, sizeof(line), "%zu,%lld,%s,%d,%d,%d,%d,%d,%d,%d,%g,%g,%g,%g,%zu,%zu\n", r.index,
                  static_cast<long long>(r.t_ns), r.skipped ? "skipped" : TrackingStateName(r.state), r.keyframe,
                  r.reinitialized, r.relocalized, r.features, r.stereo_points, r.matches, r.inliers, r.extract_ms,
                  r.track_ms, CurrentRssMiB(), HeapCommittedMiB(), r.map_keyframes, r.map_points);
    csv_->Append(line);
  }
  if (poses_ && r.T_world_cam) poses_->Append(FormatTumLine({r.t_ns, *r.T_world_cam}));
}

void RunRecorder::Flush() {
  if (csv_) csv_->Flush();
  if (poses_) poses_->Flush();
}

void RunRecorder::Finish(const SlamRunResult& result) {
  if (!out_dir_) return;
  csv_->Close();
  poses_->Close();
  if (result.trajectory.empty()) return;
  WriteTum(*out_dir_ / "trajectory.tum", result.trajectory);
  WriteKitti(*out_dir_ / "trajectory.kitti", result.trajectory);
  WriteTum(*out_dir_ / "keyframes.tum", result.keyframes);
}

SequenceResult ResultOfRun(const SlamRunResult& run, const RunRecorder::Counts& counts) {
  SequenceResult r;
  r.status = !run.error.empty() ? "failed" : run.interrupted ? "interrupted" : "ok";
  r.error = run.error;
  r.frames = run.frames;
  r.tracked = run.trajectory.size();
  r.lost = counts.lost;
  r.segments = counts.reinitialized;
  r.skipped = run.frames_skipped;
  r.keyframes = run.keyframe_count;
  r.map_points = run.point_count;
  r.loops = run.loop_closures.size();
  if (run.rig.ok) r.rig_offset_px = run.rig.offset_px;
  if (run.camera_refit.refined()) {
    r.camera_refit_k1 = run.camera_refit.k1;
    r.camera_refit_focal_scale = run.camera_refit.focal_scale;
  }
  r.fps = run.wall_s > 0 ? static_cast<double>(run.frames) / run.wall_s : 0;
  // Work per frame: the time the frame pipeline's stages and local mapping took. It is CPU time
  // where each stage has a core to itself, the figure that says how many sequences a machine
  // runs at once.
  const MappingTimes& m = run.mapping;
  const double mapping_ms = m.prepare_ms + m.triangulate_ms + m.fuse_ms + m.local_ba_ms + m.cull_ms + m.place_ms;
  if (run.frames > 0)
    r.cpu_ms_per_frame =
        (counts.extract_ms.Sum() + counts.track_ms.Sum() + mapping_ms) / static_cast<double>(run.frames);
  return r;
}

void ScoreAgainstGroundTruth(const Trajectory& gt, const Trajectory& estimate, SequenceResult* result) {
  if (gt.empty() || estimate.empty()) return;
  EvalOptions eval;
  eval.alignment = Alignment::kSE3;
  EvalResult se3, sim3;
  try {
    se3 = Evaluate(gt, estimate, eval);
    eval.alignment = Alignment::kSim3;
    sim3 = Evaluate(gt, estimate, eval);
  } catch (const Error&) {
    return;  // no pose pairs, or a degenerate alignment: no metric
  }
  result->ate_se3_m = se3.ate_m.rmse;
  result->ate_sim3_m = sim3.ate_m.rmse;
  result->scale = sim3.alignment.scale;
  result->rpe_m = se3.rpe_frames.translation_m.rmse;
  result->rpe_deg = se3.rpe_frames.rotation_deg.rmse;
  // The path over the time the trajectory covers (an interrupted run covers a part).
  double length = 0;
  for (size_t i = 1; i < gt.size(); ++i)
    if (gt[i - 1].t_ns >= estimate.front().t_ns && gt[i].t_ns <= estimate.back().t_ns)
      length += (gt[i].T_world_cam.translation() - gt[i - 1].T_world_cam.translation()).norm();
  result->path_m = length;
  if (se3.kitti.available) {
    result->kitti_t_rel_pct = se3.kitti.t_rel_percent;
    result->kitti_r_rel_deg_per_100m = se3.kitti.r_rel_deg_per_100m;
  }
}

void WriteSequenceSummary(const std::filesystem::path& out_dir, const SequenceResult& result,
                          const std::optional<Trajectory>& ground_truth) {
  if (ground_truth && !ground_truth->empty()) WriteTum(out_dir / "groundtruth.tum", *ground_truth);
  WriteResultsCsv(out_dir / "results.csv", {result});
  WriteHtmlReport(out_dir / "report.html", result.name, {ReportSequence{result, out_dir}});
}

SequenceResult RunSequence(const SequenceSpec& spec, const SequenceRunOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  SequenceResult result;
  result.name = spec.name;
  result.dataset = spec.dataset;
  result.input = options.input;
  result.sensor = spec.sensor ? SensorName(*spec.sensor) : "";
  std::optional<Trajectory> ground_truth;
  try {
    std::filesystem::create_directories(options.out_dir);
    DatasetOptions dataset_options;
    dataset_options.sensor = spec.sensor;
    dataset_options.seed = spec.seed.value_or(1);
    if (!spec.settings.empty())
      dataset_options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(spec.settings));
    std::unique_ptr<Dataset> dataset = OpenDataset(spec.dataset, dataset_options);
    CameraRefit camera_from;  // the refinement of spec.camera_from's session
    if (!spec.camera_from.empty()) dataset = DatasetThroughCameraOf(std::move(dataset), spec.camera_from, &camera_from);
    const Sensor sensor = dataset->calibration().sensor;
    result.sensor = SensorName(sensor);
    FLATSLAM_CHECK(dataset->size() > 0, "dataset ", spec.dataset, " has no frames");
    SlamOptions slam;
    slam.vocabulary = options.vocabulary;
    slam.seed = dataset_options.seed;
    ApplySlamOptionSources(&slam, dataset_options.settings.get(), sensor, 0, spec.config, spec.set);
    ground_truth = dataset->ground_truth();

    SlamRunOptions run;
    run.max_frames = spec.max_frames == 0 ? dataset->size() : std::min(spec.max_frames, dataset->size());
    run.deterministic = options.deterministic;
    run.keep_reports = false;
    run.keep_results_on_error = true;
    run.stop = options.stop;
    // As flatslam run: a monocular sequence may start over with a refined camera.
    run.check_camera = !spec.keep_camera.value_or(false) && spec.camera_from.empty();
    if (options.on_warning) {
      run.on_warning = options.on_warning;
      run.on_skipped = [&](size_t index, const std::string& reason) {
        options.on_warning("frame " + std::to_string(index) + " skipped: " + reason);
      };
    }
    RunRecorder recorder(options.out_dir);
    run.on_frame = [&](const FrameReport& r) {
      recorder.OnFrame(r);
      if (options.on_frame) options.on_frame(r);
    };
    if (options.on_opened) options.on_opened(run.max_frames);
    const SlamRunResult slam_result = RunSlam(*dataset, slam, run);
    recorder.Finish(slam_result);
    SequenceResult scored = ResultOfRun(slam_result, recorder.counts());
    if (camera_from.refined()) {
      scored.camera_refit_k1 = camera_from.k1;
      scored.camera_refit_focal_scale = camera_from.focal_scale;
    }
    scored.name = result.name;
    scored.dataset = result.dataset;
    scored.input = result.input;
    scored.sensor = result.sensor;
    if (ground_truth) ScoreAgainstGroundTruth(*ground_truth, slam_result.trajectory, &scored);
    if (slam_result.trajectory.empty() && scored.status == "ok") {
      scored.status = "failed";
      scored.error = "no frame was tracked: the map never initialized";
    }
    result = std::move(scored);
  } catch (const std::exception& e) {
    result.status = "failed";
    result.error = e.what();
  }
  result.wall_s = MsSince(start) / 1000.0;
  result.peak_rss_mib = options.peak_rss_mib ? options.peak_rss_mib() : PeakRssMiB();
  try {
    WriteSequenceSummary(options.out_dir, result, ground_truth);
  } catch (const std::exception& e) {
    if (result.status == "ok") result.status = "failed";
    result.error += std::string(result.error.empty() ? "" : "; ") + "writing the results: " + e.what();
  }
  return result;
}

}  // namespace flatslam
