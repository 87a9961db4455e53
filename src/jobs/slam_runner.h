// Runs the SLAM systems over a dataset on the frame pipeline: read + extract in parallel across
// frames, track in frame order, local mapping as a background queue.
// Concurrency: RunSlam blocks the calling thread; it uses TBB workers for the stages.
#pragma once

#include <cstddef>
#include <functional>
#include <utility>
#include <vector>

#include "io/dataset.h"
#include "systems/slam.h"

namespace flatslam {

struct SlamRunOptions {
  size_t max_frames = 0;        // 0 = every frame of the dataset; else frames [first_frame, max_frames)
  size_t first_frame = 0;       // frames before it are not read (a session continuing a saved map)
  Map* initial_map = nullptr;   // moved into the SLAM system before the first frame (Slam::AdoptMap)
  bool deterministic = false;   // map each keyframe inline in the track stage: same input, same output
  size_t max_in_flight = 0;     // frames read/extracted ahead of tracking; 0 = max(16, 4 x cores)
  // Tracking waits while more keyframes than this await local mapping, so a batch run, which
  // reads faster than real time, never tracks against a map that mapping has fallen behind on.
  int max_mapping_lag = 0;
  // Frames [first, last) are never given to SLAM (dropped frames: the camera seems to jump).
  std::vector<std::pair<size_t, size_t>> skip;
  // Tracking is declared lost at these frames (relocalization tests).
  std::vector<size_t> lose_at;
  // Called from the track stage after every frame (progress display, streamed statistics); may
  // be empty.
  std::function<void(const FrameReport&)> on_frame;
  // Keep every frame's report in SlamRunResult::reports. A caller that consumes them in on_frame
  // can turn this off, so that a session of any length holds no per-frame record but its pose.
  bool keep_reports = true;
  // Called once after every stage has drained, before RunSlam returns (e.g. to save the map);
  // may be empty.
  std::function<void(const Slam&)> on_finished;
};

struct SlamRunResult {
  std::vector<FrameReport> reports;  // one per frame given to SLAM (see skip), in order; keep_reports
  size_t frames = 0;                 // frames given to SLAM
  Trajectory trajectory;             // tracked frames, T_world_cam, refined through keyframes
  Trajectory keyframes;
  size_t keyframe_count = 0, point_count = 0;
  std::vector<LoopClosure> loop_closures;
  MappingTimes mapping;  // local mapping's time per stage
  double wall_s = 0;
};

// Runs SLAM; the Slam object is created from the dataset's calibration and options.
[[nodiscard]] SlamRunResult RunSlam(const Dataset& dataset, const SlamOptions& options, const SlamRunOptions& run);

}  // namespace flatslam
