#include "jobs/slam_runner.h"

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <mutex>

#include <tbb/task_arena.h>

#include "core/clock.h"
#include "core/error.h"
#include "jobs/background_worker.h"
#include "jobs/pipeline.h"
#include "jobs/system_graph.h"

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

}  // namespace

SlamRunResult RunSlam(const Dataset& dataset, const SlamOptions& options, const SlamRunOptions& run) {
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
    if (seq >= order.size()) return std::nullopt;
    if (run.stop && run.stop->load()) {
      result.interrupted = true;
      return std::nullopt;
    }
    Item item;
    item.index = order[seq];
    return item;
  });
  pipeline.add_parallel_stage("extract", [&](Item& item) {
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
    slam.Extract(frame, &item.frame);
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
  if (result.interrupted || !result.error.empty()) slam.AbandonBackground();
  background.Wait();
  result.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
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
  if (run.on_finished) run.on_finished(slam);
  return result;
}

}  // namespace flatslam
