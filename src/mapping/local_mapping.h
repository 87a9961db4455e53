// Local mapping: everything that writes a tracked frame's consequences into the map. The
// sightings tracking counted, the keyframes it asked for (with their points from depth or from
// the two-view initialization), then per keyframe: point upkeep, triangulation against its
// neighbours, fusion of duplicates, local bundle adjustment and culling of redundant keyframes.
// Concurrency: functions taking `Map&` write the map and need exclusive access to it; those taking
// `const Map&` need only that no writer runs; FindNewPoints and SolveLocalBundleAdjustment touch
// no map (they work on copies) and run while tracking goes on. A LocalMappingState is used by one
// caller at a time (the session's mapping node).
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <span>
#include <unordered_map>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

#include "config/context.h"
#include "ecs/map.h"
#include "frontend/frame.h"
#include "geometry/similarity.h"
#include "mapping/map_bundle_adjustment.h"
#include "optimization/bundle_adjustment.h"

namespace flatslam {

// Where local mapping spends its time, summed over the keyframes it mapped (milliseconds).
struct MappingTimes {
  size_t keyframes = 0;               // keyframes mapped
  double prepare_ms = 0;              // point statistics, covisibility, recent-point culling, copies
  double triangulate_ms = 0;          // bag of words and new points against the neighbours (no lock)
  double fuse_ms = 0;                 // adding the new points, fusing duplicates
  double local_ba_ms = 0;             // local bundle adjustment (solved without the lock)
  double cull_ms = 0;                 // redundant keyframes
  double place_ms = 0;                // keyframe database, loop detection and correction
  size_t local_ba_stopped_early = 0;  // adjustments ended early for a waiting keyframe
};

// Culled keyframes and where frames that referred to them go instead: the parent, and the culled
// keyframe's pose relative to it.
struct CulledKeyFrame {
  KeyFrameHandle parent;
  Eigen::Isometry3d T_kf_parent;
};
using CulledKeyFrames = std::unordered_map<KeyFrameHandle, CulledKeyFrame>;

// Moves *ref along culled keyframes' parents to a keyframe of `map`, composing *T_cam_ref; false
// when none is left to follow.
bool FollowToLiveKeyFrame(const Map& map, const CulledKeyFrames& culled, KeyFrameHandle* ref,
                          Eigen::Isometry3d* T_cam_ref);
// A tracked frame's pose through its reference keyframe, or through the parents of culled ones;
// the pose as tracked when no live keyframe is left to follow. `since`: how the map's world frame
// moved after the frame was recorded (SlamSession::MoveMapFrame; X_new = since * X_old): its pose
// relative to the keyframe scales with a monocular move, its pose as tracked moves.
[[nodiscard]] Eigen::Isometry3d ResolveFramePose(const Map& map, const CulledKeyFrames& culled,
                                                 const AnchoredFramePose& frame, const Similarity3& since = {});

// A monocular map's start, found by tracking from two frames: the first frame (at its pose), the
// keypoint pairs between the two, and the points triangulated from them (world coordinates;
// triangulated[k] says whether pair k has one).
struct TwoViewMap {
  TrackedFrame first;
  std::vector<std::pair<uint32_t, uint32_t>> pairs;
  std::vector<Eigen::Vector3d> X_world;
  std::vector<char> triangulated;
};

// A point triangulated for a new keyframe, not yet in the map.
struct NewPoint {
  KeyFrameHandle neighbour;
  uint32_t i1 = 0, i2 = 0;  // keypoints in the new keyframe and in the neighbour
  Eigen::Vector3d X_world;
};

// Local mapping's memory between keyframes.
struct LocalMappingState {
  std::vector<PointHandle> recent_points;  // points on probation (made by the last three keyframes)
  CulledKeyFrames culled;
  MappingTimes times;
  // Buffers kept between keyframes so their capacity is reused: copies of the new keyframe ([0])
  // and its neighbours, the local BA problem and its solver workspace.
  std::vector<KeyFrame> snapshot;
  std::vector<KeyFrameHandle> neighbours;
  MapBundleAdjustment local_ba;
  BundleAdjustmentWorkspace local_ba_workspace;
};

// Counts tracking's sightings: `visible` points were predicted in the frame, `found` were matched.
void ApplySightings(Map& map, std::span<const PointHandle> visible, std::span<const PointHandle> found);

// A new keyframe from a tracked frame: its matched points gain an observation, and keypoints with
// depth become points (all of them with all_depth_points; otherwise the close ones and at least
// the 100 nearest). The frame's point handles are updated.
KeyFrameHandle InsertKeyFrame(Map& map, LocalMappingState& state, const SystemContext& context, TrackedFrame& frame,
                              bool all_depth_points = false);
// The two keyframes and the points of a monocular initialization; `second` is the frame that
// completed it. Returns the keyframes and the number of points made.
struct InsertedTwoView {
  KeyFrameHandle first, second;
  int points = 0;
};
InsertedTwoView InsertTwoViewMap(Map& map, LocalMappingState& state, const SystemContext& context, TwoViewMap& two_view,
                                 TrackedFrame& second);

// The first step for a keyframe: statistics of its points, its covisibility, recent-point
// culling, and copies of it and its best covisible keyframes into state.snapshot for
// FindNewPoints. Returns false when the keyframe is gone. *depth_range: where its new points may lie.
bool PrepareKeyFrame(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle keyframe,
                     std::pair<double, double>* depth_range);
// Matches and triangulates the new keyframe against its neighbours, on the copies PrepareKeyFrame
// made (no map access), a task per neighbour; the result does not depend on the threads.
[[nodiscard]] std::vector<NewPoint> FindNewPoints(const LocalMappingState& state, const SystemContext& context,
                                                  std::pair<double, double> depth_range);
// Adds the new points that still fit (nothing bound or erased since), then fuses duplicates
// between the keyframe and its neighbours. add_points false: points triangulated before the map
// moved are dropped, fusion still runs.
void AddNewPointsAndFuse(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle keyframe,
                         std::span<const NewPoint> candidates, bool add_points);
// Local bundle adjustment in three steps: build the window's problem (the keyframe and its
// strongest covisible ones free, every other observer fixed, `anchor` held as the gauge), solve it
// without map access (stop_early ends it early), write the solution back erasing outliers.
// Build returns false when there is nothing to solve.
bool BuildLocalBundleAdjustment(const Map& map, LocalMappingState& state, const SystemContext& context,
                                KeyFrameHandle keyframe, KeyFrameHandle anchor);
[[nodiscard]] BundleAdjustmentResult SolveLocalBundleAdjustment(LocalMappingState& state, const SystemContext& context,
                                                                std::function<bool()> stop_early);
void ApplyLocalBundleAdjustment(Map& map, const LocalMappingState& state, const SystemContext& context,
                                const BundleAdjustmentResult& result);
// Erases covisible keyframes of `keyframe` whose points are mostly seen by three others at the
// same or a finer scale; `keep` are never erased (the map's first keyframe, tracking's reference),
// nor keyframes at either end of a loop. before_erase hears each keyframe just before it goes
// (the place index drops it); the culled record lets frames that referred to it follow its parent.
void CullKeyFrames(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle keyframe,
                   std::span<const KeyFrameHandle> keep,
                   const std::function<void(KeyFrameHandle, const KeyFrame&)>& before_erase);

}  // namespace flatslam
