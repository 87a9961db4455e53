// The camera as projections see it: pinhole intrinsics, the stereo (or RGB-D virtual) baseline
// times fx, and the scale pyramid keypoints are detected on.
// Concurrency: a plain value.
#pragma once

#include <Eigen/Core>

#include "frontend/features.h"
#include "io/types.h"

namespace flatslam {

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
