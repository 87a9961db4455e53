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

// The measured (> 0) values of a frame's keypoint depths, in a buffer of the calling thread that
// the next call reuses.
[[nodiscard]] std::vector<float>& MeasuredDepths(std::span<const float> depth);

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
