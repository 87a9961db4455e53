#include "jobs/slam_runner.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <unordered_map>

#include <tbb/task_arena.h>

#include "core/clock.h"
#include "core/error.h"
#include "io/orb_settings.h"
#include "jobs/background_worker.h"
#include "jobs/pipeline.h"
#include "jobs/system_graph.h"
#include "merge/map_merge.h"

namespace flatslam {
namespace {

struct Item {
  size_t index = 0;
  TrackedFrame frame;
  double extract_ms = 0;
  std::string unreadable;  // why the frame could not be read (empty: it was)
};

// A request for a checkpoint: the copy of the session is taken by the job itself unless it was
// already taken (captured) between two keyframes by the mapping queue.
struct CheckpointJob {
  bool captured = false;
};

// Local mapping's queue: keyframes to map, and checkpoint copies, which run there so that they
// fall between two keyframes' mapping, never half way through one (a resumed session never maps
// the rest of a keyframe its checkpoint caught half mapped).
struct MappingJob {
  KeyFrameHandle keyframe;
  bool capture = false;
};

// Keypoints a pass that checks its camera measured in the dataset's images (before any lens),
// kept for the pass that may start over: the images and the ORB options are the same, only the
// lens its frames carry differs, so those frames are made from them without reading or
// extracting again (SlamSession::ExtractFrom). Kept for the run's first
// CameraCheckWindow::kKeptFrames frames, until the run goes on. Concurrency: the extract stage
// puts and finds from many threads; one mutex.
class MeasuredFrames {
 public:
  explicit MeasuredFrames(size_t first_frame) : first_frame_(first_frame) {}

  // The pass about to run: the ORB options it extracts with (the first pass's are those of the
  // keypoints kept), the lens its frames carry, and whether it may start over (keeps more).
  void StartPass(const OrbOptions& orb, std::shared_ptr<const RefinedCamera> lens, bool may_restart) {
    const std::lock_guard<std::mutex> lock(mutex_);
    if (!orb_) orb_ = orb;
    usable_ = orb == *orb_;
    reusing_ = passes_++ > 0;
    lens_ = std::move(lens);
    if (!may_restart) StopKeepingLocked();
  }
  [[nodiscard]] bool Wants(size_t index) const {
    const std::lock_guard<std::mutex> lock(mutex_);
    return recording_ && usable_ && index >= first_frame_ && index - first_frame_ < CameraCheckWindow::kKeptFrames &&
           !kept_.contains(index);
  }
  void Put(size_t index, int64_t t_ns, Keypoints&& keypoints) {
    const std::lock_guard<std::mutex> lock(mutex_);
    if (recording_ && usable_) kept_.emplace(index, Entry{t_ns, std::move(keypoints)});
  }
  // The frame's header (index, time, this pass's lens) and its measured keypoints, if kept.
  [[nodiscard]] bool Find(size_t index, Frame* header, Keypoints* keypoints) {
    const std::lock_guard<std::mutex> lock(mutex_);
    if (!usable_) return false;
    const auto it = kept_.find(index);
    if (it == kept_.end()) return false;
    header->index = index;
    header->t_ns = it->second.t_ns;
    header->lens = lens_;
    if (recording_) {
      *keypoints = it->second.keypoints;
    } else {
      *keypoints = std::move(it->second.keypoints);  // no later pass reads it
      kept_.erase(it);
    }
    return true;
  }
  // The pass that runs goes on: nothing more is kept; the first pass's keypoints are freed, a
  // later pass's as it reads them.
  void StopKeeping() {
    const std::lock_guard<std::mutex> lock(mutex_);
    StopKeepingLocked();
  }

 private:
  struct Entry {
    int64_t t_ns = 0;
    Keypoints keypoints;
  };
  void StopKeepingLocked() {
    recording_ = false;
    if (!reusing_) kept_.clear();
  }

  const size_t first_frame_;
  std::optional<OrbOptions> orb_;  // what the kept keypoints were extracted with
  mutable std::mutex mutex_;
  bool recording_ = true, usable_ = true, reusing_ = false;
  size_t passes_ = 0;
  std::shared_ptr<const RefinedCamera> lens_;
  std::unordered_map<size_t, Entry> kept_;
};

// One session over the dataset. abandon (may be null): like run.stop, but the run is being
// replaced, not interrupted.
// at_end (may be empty): called with the session once every frame is tracked and mapped and no
// background work is left, unless the run was interrupted, failed or abandoned; counts in wall_s.
// measured (may be null): monocular frames it keeps are made from their kept keypoints, and those
// it wants are kept.
SlamRunResult RunSession(const Dataset& dataset, const SlamOptions& options, const SlamRunOptions& run,
                         const std::atomic<bool>* abandon, const std::function<void(SlamSession&)>& at_end = {},
                         MeasuredFrames* measured = nullptr) {
  const auto abandoned = [abandon] { return abandon && abandon->load(); };
  SlamSession slam(dataset.calibration(), options);
  // The run's steps and the access they declare: refused before the first frame if two that may
  // run at once conflict without the session's guard between them. Mapping inline (deterministic)
  // puts the mapping steps on the track lane, which only removes overlaps.
  SystemGraph steps;
  for (const AccessStep& step : SlamSession::Steps()) steps.Add(step);
  steps.Add({"read", Access{}, "extract", /*parallel=*/true});  // the dataset's files only
  steps.Add({"checkpoint.write", Access{}, "checkpoint"});      // the captured copy only
  // The stages built below, one per declared lane: refused if a step names a lane none runs.
  static const SystemGraph::Lane kStages[] = {
      {"extract", true}, {"track", false}, {"mapping", false}, {"background", false}, {"checkpoint", false}};
  steps.CheckStages(kStages);
  if (run.on_warning) slam.SetWarningSink(run.on_warning);
  // Global bundle adjustment runs beside the frames on its own thread (declared after slam:
  // destroyed, so waited for, first). Deterministic runs keep it inline, in mapping.
  BackgroundWorker background;
  if (!run.deterministic)
    slam.SetBackground([&background](std::function<void()> task) { background.Start(std::move(task)); });
  auto warn = [&](const std::string& message) {
    if (run.on_warning)
      run.on_warning(message);
    else
      std::fprintf(stderr, "warning: %s\n", message.c_str());
  };
  const size_t frames = run.max_frames == 0 ? dataset.size() : std::min(run.max_frames, dataset.size());
  SlamRunResult result;
  if (run.keep_reports) result.reports.reserve(frames);

  PipelineOptions pipeline_options;
  // Frames extracted ahead of tracking: a keyframe holds the track stage for its local mapping
  // (tens of milliseconds), and a deep buffer lets extraction run on meanwhile. An item is a
  // frame's keypoints (about 130 KiB at 2000 features), never its images.
  pipeline_options.max_in_flight =
      run.max_in_flight > 0 ? run.max_in_flight
                            : std::max<size_t>(16, 4 * static_cast<size_t>(tbb::this_task_arena::max_concurrency()));
  FramePipeline<Item> pipeline(pipeline_options);
  // The track stage waits on this for mapping to catch up (see max_mapping_lag); every mapped
  // keyframe, or a failed one, wakes it.
  std::mutex mapped_mutex;
  std::condition_variable mapped;
  std::function<void()> capture_between_keyframes;  // set below, with the checkpoint queue
  auto mapping = pipeline.add_background_stage<MappingJob>("mapping", [&](MappingJob& job) {
    if (job.capture) {
      capture_between_keyframes();
      return;
    }
    struct Notify {
      std::mutex& mutex;
      std::condition_variable& cv;
      ~Notify() {
        { const std::lock_guard<std::mutex> lock(mutex); }
        cv.notify_all();
      }
    } notify{mapped_mutex, mapped};
    slam.MapKeyFrame(job.keyframe);
    if (run.on_keyframe_mapped) run.on_keyframe_mapped(slam, job.keyframe);
  });
  // Checkpoint writes: one at a time, never queued behind each other (the track stage only copies
  // the session when the last copy has been written).
  std::atomic<bool> checkpoint_busy{false};
  // The copy of the session a checkpoint writes (one is written at a time), released once written:
  // with the keyframes' keypoint columns shared (SharedColumn), a fresh copy costs about a
  // millisecond, and a long session does not keep a second map in memory between checkpoints.
  // The copy is taken by a job on the mapping queue (or, with mapping inline, by the checkpoint
  // job), not by the track stage: tracking waits only while the copy reads the map (measured in
  // the frames' track_ms).
  SlamSession::State checkpoint_state;
  // Held by the track stage from Track to on_frame, and by a checkpoint's copy: a checkpoint never
  // covers a frame whose report has not been handed out.
  std::mutex between_frames;
  auto capture = [&] {
    const auto start = std::chrono::steady_clock::now();
    {
      std::lock_guard<std::mutex> lock(between_frames);
      if (run.before_checkpoint) run.before_checkpoint();
      slam.CaptureState(&checkpoint_state);
    }
    result.checkpoint_capture_ms.push_back(MsSince(start));
  };
  auto write_checkpoint = [&](bool last) {
    // The last one also covers unreadable frames at the end, which tracking never saw.
    if (last) checkpoint_state.next_frame = std::max(checkpoint_state.next_frame, result.next_frame);
    const auto start = std::chrono::steady_clock::now();
    try {
      run.on_checkpoint(checkpoint_state, checkpoint_state.next_frame);
      ++result.checkpoints;
    } catch (const std::exception& e) {
      ++result.checkpoint_failures;
      warn(std::string("checkpoint at frame ") + std::to_string(checkpoint_state.next_frame) +
           " not written, the session goes on: " + e.what());
    }
    result.checkpoint_write_ms.push_back(MsSince(start));
  };
  auto checkpoints = pipeline.add_background_stage<CheckpointJob>("checkpoint", [&](CheckpointJob& job) {
    if (!job.captured) capture();
    write_checkpoint(false);
    checkpoint_state = SlamSession::State{};
    checkpoint_busy = false;
  });
  capture_between_keyframes = [&] {
    capture();
    checkpoints.post(CheckpointJob{true});  // serializing and saving go on beside mapping
  };
  const bool checkpointing = run.checkpoint_every_s > 0 && run.on_checkpoint;
  auto last_checkpoint = std::chrono::steady_clock::now();

  // The frames SLAM sees, in order.
  std::vector<size_t> order;
  // A continued session may start past the last frame (a checkpoint taken at the end): it then
  // only gives back the trajectory it continues.
  FLATSLAM_CHECK(run.first_frame < frames || (run.initial_map && run.first_frame == frames), "first frame ",
                 run.first_frame, " is past the last frame ", frames - 1);
  if (run.initial_map) {
    // A resumed checkpoint whose last two poses are the two frames before the first one read:
    // tracking goes on from their motion instead of relocalizing.
    bool resume_tracking = false;
    const std::vector<AnchoredFramePose>& before = run.initial_frames;
    if (before.size() >= 2 && run.first_frame >= 2 && run.first_frame <= dataset.size()) {
      try {
        resume_tracking = before.back().t_ns == dataset.read(run.first_frame - 1).t_ns &&
                          before[before.size() - 2].t_ns == dataset.read(run.first_frame - 2).t_ns;
      } catch (const Error&) {
        resume_tracking = false;  // an unreadable frame there: relocalize
      }
    }
    slam.AdoptMap(std::move(*run.initial_map), run.initial_frames, resume_tracking);
    if (run.initial_global_adjustment) slam.StartGlobalBundleAdjustment();
  }
  for (size_t i = run.first_frame; i < frames; ++i) {
    const bool skipped =
        std::any_of(run.skip.begin(), run.skip.end(), [&](const auto& r) { return i >= r.first && i < r.second; });
    if (!skipped) order.push_back(i);
  }
  pipeline.set_source([&](size_t seq) -> std::optional<Item> {
    if (seq >= order.size() || abandoned()) return std::nullopt;
    if (run.stop && run.stop->load()) {
      result.interrupted = true;
      return std::nullopt;
    }
    Item item;
    item.index = order[seq];
    return item;
  });
  std::atomic<size_t> from_kept{0};
  pipeline.add_parallel_stage("extract", [&](Item& item) {
    if (abandoned()) return;  // the run is being replaced: frames in flight are dropped
    if (measured) {
      Frame header;
      Keypoints keypoints;
      if (measured->Find(item.index, &header, &keypoints)) {
        const auto start = std::chrono::steady_clock::now();
        slam.ExtractFrom(keypoints, header, &item.frame);
        item.extract_ms = MsSince(start);
        ++from_kept;
        return;
      }
    }
    Frame frame;
    try {
      frame = dataset.read(item.index);
      CheckFrame(frame, dataset.calibration());
    } catch (const Error& e) {
      if (run.strict) throw;
      item.unreadable = e.what();
      return;
    }
    const auto start = std::chrono::steady_clock::now();
    if (measured && measured->Wants(item.index)) {
      Keypoints keypoints;
      slam.Extract(frame, &item.frame, &keypoints);
      measured->Put(item.index, frame.t_ns, std::move(keypoints));
    } else {
      slam.Extract(frame, &item.frame);
    }
    item.extract_ms = MsSince(start);
  });
  // Mapping runs inline, in the track stage, where tracking would wait for every keyframe's
  // mapping anyway: with one worker (it cannot both wait and map) and without lag (a track stage
  // blocked on the wait holds a worker idle, which extraction and mapping's own parallel loops
  // could use).
  const bool inline_mapping =
      run.deterministic || run.max_mapping_lag == 0 || tbb::this_task_arena::max_concurrency() < 2;
  std::string first_unreadable;
  pipeline.add_serial_stage("track", [&](Item& item) {
    if (abandoned()) return;
    ++result.frames;
    result.next_frame = item.index + 1;
    if (!item.unreadable.empty()) {
      // Like a dropped frame: tracking never sees it.
      const std::lock_guard<std::mutex> reporting(between_frames);
      ++result.frames_skipped;
      if (first_unreadable.empty()) first_unreadable = item.unreadable;
      if (run.on_skipped) run.on_skipped(item.index, item.unreadable);
      FrameReport report;
      report.index = item.index;
      report.skipped = true;
      if (run.on_frame) run.on_frame(report);
      if (run.keep_reports) result.reports.push_back(report);
      return;
    }
    // Mapping may run behind by max_mapping_lag keyframes, none while tracking wants one.
    if (!inline_mapping) {
      std::unique_lock<std::mutex> lock(mapped_mutex);
      mapped.wait(lock, [&] {
        return slam.pending_keyframes() <= run.max_mapping_lag &&
               !(slam.keyframe_wanted() && slam.pending_keyframes() > 0);
      });
    }
    std::unique_lock<std::mutex> reporting(between_frames);
    std::optional<KeyFrameHandle> keyframe;
    if (std::find(run.lose_at.begin(), run.lose_at.end(), item.index) != run.lose_at.end()) slam.ForceLost();
    FrameReport report = slam.Track(std::move(item.frame), &keyframe);
    report.extract_ms = item.extract_ms;
    if (keyframe) {
      if (inline_mapping) {
        slam.MapKeyFrame(*keyframe);
        if (run.on_keyframe_mapped) run.on_keyframe_mapped(slam, *keyframe);
      } else
        mapping.post(MappingJob{*keyframe});
    }
    // Frames tracked while a checkpoint was copied or written: their tracking time includes any
    // wait for the map while the copy read it.
    if (checkpoint_busy.load()) {
      result.frame_ms_during_checkpoints.push_back(report.track_ms);
    } else if (checkpointing &&
               std::chrono::duration<double>(std::chrono::steady_clock::now() - last_checkpoint).count() >=
                   run.checkpoint_every_s) {
      checkpoint_busy = true;
      // With mapping inline, every frame boundary is also a boundary between keyframes.
      if (inline_mapping)
        checkpoints.post(CheckpointJob{});
      else
        mapping.post(MappingJob{KeyFrameHandle::null(), true});
      last_checkpoint = std::chrono::steady_clock::now();
    }
    if (run.on_frame) run.on_frame(report);
    if (run.keep_reports) result.reports.push_back(report);
  });
  result.next_frame = run.first_frame;
  const auto start = std::chrono::steady_clock::now();
  try {
    pipeline.run();
  } catch (const Error& e) {
    if (!run.keep_results_on_error) throw;
    result.error = e.what();
  }
  if (result.interrupted || !result.error.empty() || abandoned()) slam.AbandonBackground();
  background.Wait();
  if (at_end && !result.interrupted && result.error.empty() && !abandoned() && result.frames > result.frames_skipped)
    at_end(slam);
  result.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  result.frames_from_kept_keypoints = from_kept.load();
  if (result.error.empty() && result.frames > 0 && result.frames_skipped == result.frames)
    Fail("none of the ", result.frames, " frames of ", dataset.name(), " could be read; the first: ", first_unreadable);
  result.trajectory = slam.FrameTrajectory();
  result.keyframes = slam.KeyFrameTrajectory();
  result.keyframe_count = slam.map().keyframes().size();
  result.point_count = slam.map().points().size();
  result.loop_closures = slam.loop_closures();
  result.mapping = slam.mapping_times();
  if (dataset.calibration().sensor == Sensor::kStereo)
    result.rig = FitDisparityOffset(slam.map(), slam.context().geometry);
  // The last checkpoint: the whole session as it ends.
  if (checkpointing && result.frames > result.frames_skipped) {
    capture();
    write_checkpoint(true);
  }
  result.calibration = dataset.calibration();
  if (run.on_finished) run.on_finished(slam);
  return result;
}

// A dataset another owns, to be seen through a refined camera (ApplyOrbSettings owns its input).
class BorrowedDataset final : public Dataset {
 public:
  explicit BorrowedDataset(const Dataset& dataset) : dataset_(dataset) {}
  [[nodiscard]] std::string name() const override { return dataset_.name(); }
  [[nodiscard]] const Calibration& calibration() const override { return dataset_.calibration(); }
  [[nodiscard]] size_t size() const override { return dataset_.size(); }
  [[nodiscard]] Frame read(size_t i) const override { return dataset_.read(i); }
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return dataset_.ground_truth(); }

 private:
  const Dataset& dataset_;
};

// The first pass of a run that checks its camera: holds back what on_frame and on_skipped would
// hear until the check has decided, then passes it on (the run goes on) or drops it (the run
// starts over). Callbacks come from the track stage and the mapping lane; one mutex orders them.
class CameraCheckPass {
 public:
  CameraCheckPass(const SlamRunOptions& run, size_t frames, MeasuredFrames* measured)
      : run_(run),
        window_frames_(static_cast<size_t>(CameraCheckWindow::kFrameShare * static_cast<double>(frames))),
        measured_(measured) {}

  // The options of the first pass: run's, with its callbacks wrapped.
  [[nodiscard]] SlamRunOptions Options() {
    SlamRunOptions first = run_;
    first.on_frame = [this](const FrameReport& report) {
      Hear([this, report] { if (run_.on_frame) run_.on_frame(report); }, true);
    };
    first.on_skipped = [this](size_t index, const std::string& reason) {
      Hear([this, index, reason] { if (run_.on_skipped) run_.on_skipped(index, reason); }, false);
    };
    first.on_keyframe_mapped = [this](SlamSession& slam, KeyFrameHandle keyframe) {
      if (run_.on_keyframe_mapped) run_.on_keyframe_mapped(slam, keyframe);
      Check(slam);
    };
    if (run_.on_checkpoint)
      first.on_checkpoint = [this](const SlamSession::State& state, size_t next_frame) {
        {
          const std::lock_guard<std::mutex> lock(mutex_);
          if (state_ != kGoOn) return;  // a checkpoint describes the run that goes on
        }
        run_.on_checkpoint(state, next_frame);
      };
    first.on_finished = [this](const SlamSession& slam) {
      {
        const std::lock_guard<std::mutex> lock(mutex_);
        // Interrupted while starting over: what the first pass computed is the result.
        if (state_ == kRestart && !(run_.stop && run_.stop->load())) return;
        GoOnLocked();
      }
      if (run_.on_finished) run_.on_finished(slam);
    };
    return first;
  }

  // Passes on what is held: the first pass ended in an error, and what it tracked is the result.
  void Release() {
    const std::lock_guard<std::mutex> lock(mutex_);
    GoOnLocked();
  }

  [[nodiscard]] const std::atomic<bool>* abandon() const { return &abandon_; }
  [[nodiscard]] bool restart() const { return state_ == kRestart; }
  [[nodiscard]] const CameraCheck& last_check() const { return last_; }
  [[nodiscard]] size_t frames_at_restart() const { return frames_at_restart_; }
  // The keyframe count of the schedule's next check (the mapping lane's; read after the pass).
  [[nodiscard]] size_t next_check() const { return next_check_; }

 private:
  // A call for run's on_frame or on_skipped: held while undecided, else made (outside the lock).
  // A frame's call counts towards the window, whose end decides that the run goes on.
  void Hear(std::function<void()> call, bool frame) {
    std::unique_lock<std::mutex> lock(mutex_);
    if (frame && ++frames_seen_ > window_frames_ && state_ == kUndecided) GoOnLocked();
    if (state_ != kGoOn) {
      held_.push_back(std::move(call));
      return;
    }
    lock.unlock();
    call();
  }

  // On the mapping lane after each keyframe: a check when the map has reached the next count.
  void Check(SlamSession& slam) {
    {
      const std::lock_guard<std::mutex> lock(mutex_);
      if (state_ != kUndecided) return;
    }
    CameraCheck check;
    size_t keyframes = 0;
    const CameraGeometry& geometry = slam.context().geometry;
    slam.ReadMap([&](const Map& map) {
      keyframes = map.keyframes().size();
      if (keyframes < next_check_) return;
      CameraCheckOptions options;
      options.max_points = CameraCheckWindow::kMaxPoints;
      check = CheckCameraModel(map, geometry, options);
    });
    if (keyframes < next_check_) return;
    next_check_ = std::max(next_check_ + 1, next_check_ * 3 / 2);  // 4, 6, 9, 13, 19, 28, 42, 63
    const std::lock_guard<std::mutex> lock(mutex_);
    if (state_ != kUndecided) return;
    last_ = check;
    if (CameraCheckWindow::Refits(check, geometry.camera)) {
      state_ = kRestart;  // what is held stays held: dropped, unless a stop keeps this pass
      frames_at_restart_ = frames_seen_;
      abandon_ = true;
    } else if (next_check_ > CameraCheckWindow::kMaxKeyFrames) {
      GoOnLocked();
    }
  }

  // The first pass is the run: everything held goes out, in order, before anything heard later.
  void GoOnLocked() {
    state_ = kGoOn;
    measured_->StopKeeping();  // no pass starts over after this one
    for (const auto& call : held_) call();
    held_.clear();
  }

  const SlamRunOptions& run_;
  const size_t window_frames_;
  MeasuredFrames* const measured_;
  std::mutex mutex_;
  enum State { kUndecided, kGoOn, kRestart } state_ = kUndecided;
  std::vector<std::function<void()>> held_;
  size_t frames_seen_ = 0, frames_at_restart_ = 0;
  size_t next_check_ = CameraCheckWindow::kFirst;  // mapping lane only
  CameraCheck last_;
  std::atomic<bool> abandon_{false};
};

}  // namespace

bool CameraCheckWindow::Refits(const CameraCheck& check, const PinholeCamera& camera) {
  const double shift = CameraCheckCornerShiftPx(check, camera);
  return CameraCheckDisagrees(check) && shift >= kMinCornerShiftPx &&
         shift <= kMaxCornerShiftShare * 0.5 * std::hypot(camera.width, camera.height);
}

namespace {

// What the check after the last frame found and did (RunSlam).
struct EndRefinement {
  CameraCheck check;
  bool refined = false;
  CameraRefit refit;  // the dataset's refinement, composed, when refined
  Calibration calibration;
  size_t keypoints = 0;
  double max_shift_px = 0, ms = 0;
};

// The whole map's check after the last frame, once it holds at least min_keyframes: a map that
// disagrees with its camera by what CameraCheckWindow::Refits accepts has its keypoints moved
// from the camera it saw (given, refined by `refit`) into the refinement the map asks for, and is
// adjusted in it to convergence (ReexpressMapCamera, as a merge re-expresses a map), which takes
// out what keyframes and points had bent to fit the old model.
EndRefinement RefineCameraAtEnd(SlamSession& slam, const Calibration& seen, const PinholeCamera& given,
                                const CameraRefit& refit, size_t min_keyframes) {
  EndRefinement out;
  const auto start = std::chrono::steady_clock::now();
  const CameraGeometry& geometry = slam.context().geometry;
  bool checked = false;
  slam.ReadMap([&](const Map& map) {
    if (map.keyframes().size() < min_keyframes) return;
    CameraCheckOptions options;
    options.max_points = CameraCheckWindow::kMaxPoints;
    out.check = CheckCameraModel(map, geometry, options);
    checked = true;
  });
  if (checked && CameraCheckWindow::Refits(out.check, geometry.camera)) {
    slam.EditMapAfterLastFrame([&](Map& map) {
      const MapCameraRefinement r = RefineMapCamera(map, seen, slam.context().map_scales, given, refit,
                                                    CameraRefit{out.check.focal_scale, out.check.k1});
      out.refit = r.refit;
      out.calibration = r.calibration;
      out.keypoints = r.change.keypoints;
      out.max_shift_px = r.change.max_shift_px;
    });
    out.refined = true;
  }
  out.ms = MsSince(start);
  return out;
}

}  // namespace

SlamRunResult RunSlam(const Dataset& dataset, const SlamOptions& options, const SlamRunOptions& run) {
  // A continued session checks its whole map after its last frame too (composing onto the
  // refinement the continued map's session made), but never starts over; one that only localizes
  // leaves the map as it is, and one whose map's given camera is not recorded cannot be moved.
  const bool continued = run.initial_map != nullptr;
  const bool movable = !run.continued_refit.refined() || run.continued_given.valid();
  if (!run.check_camera || dataset.calibration().sensor != Sensor::kMonocular ||
      (continued && (options.localization_only || !movable)))
    return RunSession(dataset, options, run, nullptr);
  // The camera the dataset gave, before any refinement.
  const PinholeCamera given = continued && run.continued_refit.refined() ? run.continued_given : dataset.calibration().camera;
  const size_t end = run.max_frames > 0 ? std::min(run.max_frames, dataset.size()) : dataset.size();
  const size_t frames = end > run.first_frame ? end - run.first_frame : 0;
  CameraRefit refit = continued ? run.continued_refit : CameraRefit{};  // the refinements so far, composed
  std::unique_ptr<Dataset> refined;   // the dataset seen through refit
  CameraCheck last_check;             // the last check any pass made, and its pass's camera
  PinholeCamera checked_camera = dataset.calibration().camera;
  size_t restarts = 0, frames_before_restart = 0;
  double wall_s = 0;
  SlamRunResult result;
  EndRefinement at_last;
  // After the last frame of the pass that goes on: the whole map checked once more (once it
  // reached the window's next count: a map no larger than the last check's says nothing new).
  auto at_end = [&](const Dataset& seen, const std::function<size_t()>& min_keyframes) {
    return [&, min_keyframes](SlamSession& slam) {
      at_last = RefineCameraAtEnd(slam, seen.calibration(), given, refit, min_keyframes());
      if (at_last.refined && run.on_camera_refined) run.on_camera_refined(at_last.refit, at_last.calibration, false);
    };
  };
  // The first pass's keypoints, for a pass that starts over (a continued session never does).
  MeasuredFrames measured(run.first_frame);
  std::shared_ptr<const RefinedCamera> lens;  // the lens the frames of `refined` carry
  for (;;) {
    const Dataset& seen = refined ? *refined : dataset;
    const bool last = continued || restarts == CameraCheckWindow::kMaxRestarts;
    measured.StartPass(ResolvedOptions(options, seen.calibration()).orb, lens, !last);
    if (last) {
      result = RunSession(seen, options, run, nullptr, at_end(seen, [] { return CameraCheckWindow::kFirst; }),
                          continued ? nullptr : &measured);
      wall_s += result.wall_s;
      break;
    }
    CameraCheckPass pass(run, frames, &measured);
    try {
      result = RunSession(seen, options, pass.Options(), pass.abandon(),
                          at_end(seen, [&pass] { return pass.next_check(); }), &measured);
    } catch (...) {
      pass.Release();  // what the frames before the error gave is still heard
      throw;
    }
    wall_s += result.wall_s;
    if (pass.last_check().ok || !last_check.ok) {
      last_check = pass.last_check();
      checked_camera = seen.calibration().camera;
    }
    if (!pass.restart()) {
      if (pass.abandon()->load()) result.interrupted = true;  // stopped while starting over
      break;
    }
    // Start over through the dataset's images once more, with the refinement composed into one.
    refit = ThenRefit(refit, CameraRefit{pass.last_check().focal_scale, pass.last_check().k1});
    ++restarts;
    frames_before_restart += pass.frames_at_restart();
    lens = std::make_shared<const RefinedCamera>(dataset.calibration().camera, refit);
    refined = ApplyCameraRefit(std::make_unique<BorrowedDataset>(dataset), lens);
    if (run.on_camera_refined) run.on_camera_refined(refit, refined->calibration(), true);
  }
  result.camera_check = last_check;
  result.camera_checked = checked_camera;
  result.camera_refit = result.camera_refit_tracked = refit;
  result.camera_check_at_end = at_last.check;
  result.camera_tracked = result.calibration.camera;
  result.camera_end_ms = at_last.ms;
  if (at_last.refined) {
    result.camera_refit = at_last.refit;
    result.calibration = at_last.calibration;
    result.camera_refined_at_end = true;
    result.camera_end_keypoints = at_last.keypoints;
    result.camera_end_max_shift_px = at_last.max_shift_px;
  }
  result.camera_restarts = restarts;
  result.frames_before_restart = frames_before_restart;
  result.wall_s = wall_s;  // every pass's
  return result;
}

}  // namespace flatslam
