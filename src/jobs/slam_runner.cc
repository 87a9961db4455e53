#include "jobs/slam_runner.h"

#include <algorithm>
#include <chrono>
#include <thread>

#include <tbb/task_arena.h>

#include "core/error.h"
#include "jobs/pipeline.h"

namespace flatslam {
namespace {

struct Item {
  size_t index = 0;
  TrackedFrame frame;
  double extract_ms = 0;
};

}  // namespace

SlamRunResult RunSlam(const Dataset& dataset, const SlamOptions& options, const SlamRunOptions& run) {
  Slam slam(dataset.calibration(), options);
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
  auto mapping =
      pipeline.add_background_stage<KeyFrameHandle>("mapping", [&](KeyFrameHandle& kf) { slam.MapKeyFrame(kf); });
  // The frames SLAM sees, in order.
  std::vector<size_t> order;
  FLATSLAM_CHECK(run.first_frame < frames, "first frame ", run.first_frame, " is past the last frame ", frames - 1);
  if (run.initial_map) slam.AdoptMap(std::move(*run.initial_map));
  for (size_t i = run.first_frame; i < frames; ++i) {
    const bool skipped =
        std::any_of(run.skip.begin(), run.skip.end(), [&](const auto& r) { return i >= r.first && i < r.second; });
    if (!skipped) order.push_back(i);
  }
  pipeline.set_source([&](size_t seq) -> std::optional<Item> {
    if (seq >= order.size()) return std::nullopt;
    Item item;
    item.index = order[seq];
    return item;
  });
  pipeline.add_parallel_stage("extract", [&](Item& item) {
    const Frame frame = dataset.read(item.index);
    const auto start = std::chrono::steady_clock::now();
    slam.Extract(frame, &item.frame);
    item.extract_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  });
  // One worker cannot both wait in the track stage and run mapping: map inline then.
  const bool inline_mapping = run.deterministic || tbb::this_task_arena::max_concurrency() < 2;
  pipeline.add_serial_stage("track", [&](Item& item) {
    // Mapping may run behind by max_mapping_lag keyframes, none while tracking wants one.
    while (!inline_mapping && (slam.pending_keyframes() > run.max_mapping_lag ||
                               (slam.keyframe_wanted() && slam.pending_keyframes() > 0)))
      std::this_thread::sleep_for(std::chrono::microseconds(200));
    std::optional<KeyFrameHandle> keyframe;
    if (std::find(run.lose_at.begin(), run.lose_at.end(), item.index) != run.lose_at.end()) slam.ForceLost();
    FrameReport report = slam.Track(std::move(item.frame), &keyframe);
    report.extract_ms = item.extract_ms;
    if (keyframe) {
      if (inline_mapping) slam.MapKeyFrame(*keyframe);
      else mapping.post(*keyframe);
    }
    if (run.on_frame) run.on_frame(report);
    ++result.frames;
    if (run.keep_reports) result.reports.push_back(report);
  });
  const auto start = std::chrono::steady_clock::now();
  pipeline.run();
  slam.WaitForBackground();
  result.wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  result.trajectory = slam.FrameTrajectory();
  result.keyframes = slam.KeyFrameTrajectory();
  result.keyframe_count = slam.map().keyframes().size();
  result.point_count = slam.map().points().size();
  result.loop_closures = slam.loop_closures();
  result.mapping = slam.mapping_times();
  if (run.on_finished) run.on_finished(slam);
  return result;
}

}  // namespace flatslam
