// The camera as projections see it: pinhole intrinsics, the stereo (or RGB-D virtual) baseline
// times fx, and the scale pyramid keypoints are detected on.
// Concurrency: a plain value.
#pragma once

#include <limits>
#include <span>
#include <vector>

#include <Eigen/Core>

#include "frontend/features.h"
#include "io/types.h"

namespace flatslam {

// ORB-SLAM2's close-depth threshold for KITTI and EuRoC, in baselines: the default stereo cut.
inline constexpr double kFarStereoBaselines = 35;
// A matched disparity under this many pixels of its keypoint's pyramid level counts as monocular
// in optimization: there the sub-pixel step (a parabola through the three SAD values around the
// minimum, which near the minimum are V-shaped) pulls the disparity towards the whole pixel at
// zero, a bias of -0.09 to -0.15 px on rendered rigs that no noise model averages out
// (docs/STATUS.md, "Defaults from the camera"). One pixel of the level is the step's own unit.
inline constexpr double kFarStereoLevelPixels = 1;

// The measured (> 0) values of a frame's keypoint depths, in a buffer of the calling thread that
// the next call reuses.
[[nodiscard]] std::vector<float>& MeasuredDepths(std::span<const float> depth);

// How stereo observations enter optimization. A stereo keypoint deeper than FarDepth() counts
// as monocular: its disparity is a few pixels, where a tenth of a pixel of rectification error is
// a percent of depth. The cut is fixed_far_m, but never nearer than the frame's median measured
// depth, so that where most texture is far (a motorway) the scale does not rest on a few road
// points. A stereo rig's keypoint whose disparity is under min_level_px pixels of its pyramid
// level counts as monocular too (kFarStereoLevelPixels); on a rig short for its scene those lie
// nearer than the median. RGB-D and monocular keep every observation as it is (fixed_far_m
// infinite, min_level_px 0).
struct StereoDepthRule {
  double fixed_far_m = std::numeric_limits<double>::infinity();
  double min_level_px = 0;

  // far_stereo_baselines x baseline and far_stereo_level_px for a stereo rig (0: no cut);
  // neither otherwise.
  [[nodiscard]] static StereoDepthRule ForRig(bool stereo, double baseline_m, double far_stereo_baselines,
                                              double far_stereo_level_px = kFarStereoLevelPixels);
  // The cut for one frame or keyframe, from its keypoint depths (<= 0: none measured).
  [[nodiscard]] double FarDepth(std::span<const float> depth) const;
  // The right-image coordinate an optimization uses for a keypoint at u on a level of level_scale
  // (right_u < 0: none measured): none beyond far_depth or under min_level_px of its level.
  [[nodiscard]] double RightU(float u, float right_u, float depth, double far_depth, double level_scale) const {
    if (right_u < 0 || depth > far_depth || u - right_u < min_level_px * level_scale) return -1;
    return right_u;
  }
};

// What a projection needs: camera, stereo baseline times fx (0 = monocular), pyramid.
struct CameraGeometry {
  PinholeCamera camera;
  double bf = 0;  // baseline * fx; right_u = u - bf / z
  ScalePyramid pyramid;

  // The rig a calibration describes: a stereo pair's baseline, RGB-D depth as a virtual right
  // image rgbd_virtual_baseline_m to the right, none for a monocular camera.
  [[nodiscard]] static CameraGeometry FromCalibration(const Calibration& calibration, double rgbd_virtual_baseline_m,
                                                      const ScalePyramid& pyramid) {
    CameraGeometry g;
    g.camera = calibration.camera;
    const double baseline = calibration.sensor == Sensor::kStereo ? calibration.baseline_m
                            : calibration.sensor == Sensor::kRgbd ? rgbd_virtual_baseline_m
                                                                  : 0.0;
    g.bf = baseline * calibration.camera.fx;
    g.pyramid = pyramid;
    return g;
  }

  [[nodiscard]] bool InImage(double u, double v) const {
    return u >= 0 && v >= 0 && u < camera.width && v < camera.height;
  }
  // Pixel of a camera-frame point; false when it is behind the camera or outside the image.
  [[nodiscard]] bool Project(const Eigen::Vector3d& Xc, double* u, double* v) const {
    if (Xc.z() <= 0) return false;
    const Eigen::Vector2d uv = camera.Project(Xc);
    *u = uv.x();
    *v = uv.y();
    return InImage(*u, *v);
  }
};

}  // namespace flatslam
