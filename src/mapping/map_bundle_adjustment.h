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
