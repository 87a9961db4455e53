// What every system of one session reads and none writes: the options resolved for the camera and
// what follows from the calibration (projection geometry, the stereo depth rule, map scales).
// Concurrency: built once with the session, then read-only on any thread.
#pragma once

#include <cstddef>
#include <span>

#include "config/options.h"
#include "ecs/map.h"
#include "geometry/camera.h"
#include "io/calibration.h"

namespace flatslam {

struct SystemContext {
  Calibration calibration;
  SlamOptions options;  // resolved for the calibration (ResolvedOptions)
  CameraGeometry geometry;
  StereoDepthRule stereo_depth;  // which stereo observations optimization keeps as stereo
  MapScales map_scales;

  // Checks the resolved options (naming the field that fails) and the calibration; throws
  // flatslam::Error. `pyramid` is the extractor's scale pyramid.
  SystemContext(const Calibration& calibration, const SlamOptions& resolved, const ScalePyramid& pyramid);

  [[nodiscard]] bool monocular() const { return calibration.sensor == Sensor::kMonocular; }
  // The stereo or RGB-D virtual baseline in metres; 0 for a monocular camera.
  [[nodiscard]] double baseline_m() const { return geometry.bf / geometry.camera.fx; }
  // Depth below which a measured depth is reliable ("close" points): close_depth_baselines x
  // baseline; 0 for a monocular camera.
  [[nodiscard]] double CloseDepth() const {
    return monocular() ? 0.0 : options.close_depth_baselines * geometry.bf / geometry.camera.fx;
  }
  // The close depth of one frame, from its keypoint depths (<= 0: none measured): CloseDepth(),
  // or farther where fewer than kNearestCloseKeypoints measured keypoints lie that near, so that
  // its kNearestCloseKeypoints nearest always count as close (see kNearestCloseKeypoints).
  [[nodiscard]] double CloseDepth(std::span<const float> depth) const;
};

// A keyframe with depth makes map points of all its close keypoints and of at least its 100
// nearest (ORB-SLAM2's rule), and the keyframe rule counts the same nearest keypoints as close.
// Close depth in baselines alone leaves a rig short for its scene with few close keypoints: a
// 0.25 m baseline on a motorway counts those under 8.75 m, fewer than 70 in a frame, so the rule
// "under 100 close points tracked, over 70 untracked" never fired, keyframes came 17 m apart, and
// the map held almost only points 100 m and more away, which fix the rotation but not the
// translation (docs/STATUS.md, "Defaults from the camera").
inline constexpr size_t kNearestCloseKeypoints = 100;

}  // namespace flatslam
