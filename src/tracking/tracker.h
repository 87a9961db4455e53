// Tracking: the pose of each frame against the map (motion model, reference keyframe, local map,
// relocalization through the place index, initialization of a new map segment), and whether the
// frame should become a keyframe. Tracking reads the map and never writes it: what the map should
// gain from a frame (sightings, keyframes, a monocular initial map) is returned in TrackResult for
// the mapping system to write (mapping/local_mapping.h).
// Concurrency: TrackFrame and FinishFrame read the map and the keyframe database and write only
// their TrackerState and the frame; the caller keeps writers of the map out while they run. One
// TrackerState per session, used by one thread at a time (the session's track node).
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <random>
#include <vector>

#include <Eigen/Geometry>

#include "config/context.h"
#include "ecs/map.h"
#include "frontend/frame.h"
#include "mapping/local_mapping.h"
#include "place/keyframe_database.h"

namespace flatslam {

enum class TrackingState { kNotInitialized, kOk, kLost };
[[nodiscard]] const char* TrackingStateName(TrackingState state);

// Per-frame outcome of tracking, for stats.csv and the run summary.
struct FrameReport {
  size_t index = 0;
  int64_t t_ns = 0;
  TrackingState state = TrackingState::kNotInitialized;
  bool keyframe = false;
  bool reinitialized = false;  // tracking was lost and a new map segment started here
  bool relocalized = false;    // tracking was lost and resumed in the existing map here
  int features = 0;
  int stereo_points = 0;  // keypoints with depth
  int matches = 0;        // map points matched before the final pose optimization
  int inliers = 0;
  size_t map_keyframes = 0;  // keyframes in the map after this frame
  size_t map_points = 0;     // map points after this frame
  double extract_ms = 0;
  double track_ms = 0;
  // The frame's image could not be read; it was never given to tracking (see SlamRunOptions).
  bool skipped = false;
  // The pose tracking gave the frame (T_world_cam), when it joined the trajectory.
  std::optional<Eigen::Isometry3d> T_world_cam;
  // How many times the map had moved to another frame (SlamSession::MoveMapFrame) when the frame
  // was tracked: T_world_cam is in the world frame after that many moves.
  uint32_t map_frame = 0;
};

// Tracking's memory from one frame to the next.
struct TrackerState {
  TrackingState state = TrackingState::kNotInitialized;
  std::optional<TrackedFrame> last_frame;
  std::optional<Eigen::Isometry3d> velocity;  // T_cur_last of the previous step
  // The time (ns) that step took; the prediction continues the velocity for the time since the
  // last frame (a dropped frame doubles it). 0: unknown, the velocity is used as it is.
  int64_t velocity_dt_ns = 0;
  // The keyframe sharing most points with the last frame: frames are anchored at it, and local
  // mapping never culls it.
  KeyFrameHandle reference_keyframe;
  // The first keyframe of the map: the gauge of bundle adjustment, never culled.
  KeyFrameHandle first_keyframe;
  size_t last_keyframe_frame = 0;  // input index of the last keyframe made
  size_t segment_keyframes = 0;    // keyframes made since the current map segment started
  // The most local-map inliers a frame tracked since the last keyframe (what that keyframe gave).
  int keyframe_peak_inliers = 0;
  std::vector<KeyFrameHandle> local_keyframes;
  std::vector<PointHandle> local_points;
  int last_inliers = 0;  // of the last frame's local-map tracking
  // How far (pixels, median over the matched points) the motion model's prediction landed from
  // the tracked pose: the largest of the recent frames', halving with each frame after it.
  float prediction_error_px = 0;
  std::optional<TrackedFrame> init_frame;  // monocular: first frame of the two-view initialization
  std::mt19937_64 rng;                     // RANSAC of the monocular initialization
  int lost_frames = 0;
  bool force_lost = false;
  bool allow_new_segments = true;  // false on an adopted map and in localization-only mode

  explicit TrackerState(uint64_t seed = 1) : rng(seed) {}
};

// What tracking asks of the mapping system for one frame.
struct TrackResult {
  FrameReport report;  // the map sizes, keyframe flag and time are the caller's to fill
  bool ok = false;     // the frame has a pose (FinishFrame records it)
  // Sightings: points predicted in the frame and points matched (none in localization-only mode).
  std::vector<PointHandle> visible, found;
  // What to insert into the map: nothing, a keyframe from the frame (kFirstKeyFrame: a new map
  // segment, every keypoint with depth becomes a point), or a monocular two-view map.
  enum class Insert : uint8_t { kNone, kKeyFrame, kFirstKeyFrame, kTwoView } insert = Insert::kNone;
  std::optional<TwoViewMap> two_view;
  // The inserted keyframe goes on to local mapping.
  bool map_keyframe = false;
  // Tracking wanted a keyframe but local mapping was busy (set when the keyframe rule ran).
  std::optional<bool> keyframe_wanted;
};

// Tracks one frame against the map; `pending_keyframes` are keyframes local mapping has not
// finished. Writes the frame's pose and point handles and the tracker state.
[[nodiscard]] TrackResult TrackFrame(const Map& map, const KeyFrameDatabase& database, const SystemContext& context,
                                     TrackerState& state, TrackedFrame& frame, int pending_keyframes);

// After the mapping system inserted what `result` asked for (`inserted`: the keyframes it made,
// second only for a two-view map): updates the tracker state and returns the frame's pose record
// when it has one. *new_keyframe is the keyframe to map, if any. The frame becomes the last frame.
[[nodiscard]] std::optional<AnchoredFramePose> FinishFrame(const Map& map, TrackerState& state, TrackedFrame&& frame,
                                                           TrackResult& result, const InsertedTwoView& inserted,
                                                           std::optional<KeyFrameHandle>* new_keyframe);

// Resumes tracking where a checkpointed session stopped, so that its continuation tracks on
// instead of relocalizing: the last frame stands in as its reference keyframe's keypoints and
// points, at the last frame's pose (through the reference), and the motion model comes from the
// last two frames' poses as tracked. `previous` and `last` must be consecutive input frames.
// Returns false, leaving the state as it was, when the reference keyframe is not in the map.
bool ResumeTracking(const Map& map, const SystemContext& context, const AnchoredFramePose& previous,
                    const AnchoredFramePose& last, TrackerState& state);

// Relocalization: candidates from the place index by bag of words, then for each a bag-of-words
// match, PnP RANSAC and pose optimization with a projection search. Returns the keyframe the frame
// was found at (its pose and point handles set), or none.
[[nodiscard]] std::optional<KeyFrameHandle> Relocalize(const Map& map, const KeyFrameDatabase& database,
                                                       const SystemContext& context, TrackedFrame& frame);

// Optimizes the frame's pose over its matched points; outliers lose their point. Returns inliers.
int OptimizeFramePose(const Map& map, const SystemContext& context, TrackedFrame& frame);

}  // namespace flatslam
