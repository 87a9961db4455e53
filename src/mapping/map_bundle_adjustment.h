// Bundle adjustment over part of a map: the one place that turns keyframes, points and
// observations into a BundleAdjustmentProblem and writes a solution back. Local mapping (the
// window around a new keyframe), global BA after a loop and the weld of a map merge all use it.
// Concurrency: BuildMapBundleAdjustment reads the map (the caller keeps writers out while it
// runs); ApplyMapBundleAdjustment writes it (the caller holds exclusive access). The solve in
// between needs no access to the map.
#pragma once

#include <cstddef>
#include <limits>
#include <span>
#include <vector>

#include "ecs/map.h"
#include "optimization/bundle_adjustment.h"
#include "geometry/camera.h"

namespace flatslam {

// ORB-SLAM2's close-depth threshold for KITTI and EuRoC, in baselines: the default stereo cut.
inline constexpr double kFarStereoBaselines = 35;

// How stereo observations enter optimization. A stereo keypoint deeper than FarDepth() counts
// as monocular: its disparity is a few pixels, where a tenth of a pixel of rectification error is
// a percent of depth. The cut is fixed_far_m, but never nearer than the frame's median measured
// depth, so that where most texture is far (a motorway) the scale does not rest on a few road
// points. RGB-D and monocular keep every observation as it is (fixed_far_m infinite).
struct StereoDepthRule {
  double fixed_far_m = std::numeric_limits<double>::infinity();

  // far_stereo_baselines x baseline for a stereo rig (0 baselines: no cut); infinite otherwise.
  [[nodiscard]] static StereoDepthRule ForRig(bool stereo, double baseline_m, double far_stereo_baselines);
  // The cut for one frame or keyframe, from its keypoint depths (<= 0: none measured).
  [[nodiscard]] double FarDepth(std::span<const float> depth) const;
  // The right-image coordinate an optimization uses for a keypoint: none beyond far_depth.
  [[nodiscard]] static double RightU(float right_u, float depth, double far_depth) {
    return depth > far_depth ? -1 : right_u;
  }
};

// A problem with the map handles of its poses and points (same order as problem.poses/points).
struct MapBundleAdjustment {
  BundleAdjustmentProblem problem;
  std::vector<KeyFrameHandle> keyframes;
  std::vector<PointHandle> points;

  void Clear() {
    problem.poses.clear();
    problem.points.clear();
    problem.observations.clear();
    keyframes.clear();
    points.clear();
  }
};

// Fills *out (cleared first, buffers kept) with: the keyframes of `free` as free poses, in that
// order (`anchor` among them held fixed: the gauge); the live points they see with at least
// min_observations observers; every observation of those points, a keyframe outside `free`
// entering as a fixed pose. Dead handles in `free` are skipped.
void BuildMapBundleAdjustment(const Map& map, const CameraGeometry& geometry, const StereoDepthRule& stereo,
                              std::span<const KeyFrameHandle> free, KeyFrameHandle anchor, size_t min_observations,
                              MapBundleAdjustment* out);

// Writes a successful solution back: with erase_outliers, the observations the solver rejected
// are erased from the map first; then every free pose and every point. Keyframes and points that
// died since the problem was built are skipped. Returns the number of outlier observations. Point
// statistics (normal, depth range) are left to the caller.
size_t ApplyMapBundleAdjustment(const MapBundleAdjustment& ba, const BundleAdjustmentResult& result,
                                bool erase_outliers, Map* map);

}  // namespace flatslam
