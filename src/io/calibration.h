// The sensor and camera a dataset was recorded with, without any image type: what map snapshots
// and exports store (src/storage) needs no OpenCV header.
// Concurrency: plain values.
#pragma once

#include <string>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace flatslam {

enum class Sensor { kMonocular, kStereo, kRgbd };

[[nodiscard]] const char* SensorName(Sensor sensor);
// Parses "mono"/"monocular", "stereo", "rgbd"; throws flatslam::Error otherwise.
[[nodiscard]] Sensor ParseSensor(const std::string& name);

// Pinhole camera of rectified, undistorted images. Pixel (u, v) = (fx x/z + cx, fy y/z + cy).
struct PinholeCamera {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  int width = 0, height = 0;

  [[nodiscard]] Eigen::Matrix3d K() const {
    Eigen::Matrix3d k;
    k << fx, 0, cx, 0, fy, cy, 0, 0, 1;
    return k;
  }
  [[nodiscard]] bool valid() const { return fx > 0 && fy > 0 && width > 0 && height > 0; }
  // Pixel of a camera-frame point in front of the camera (z > 0; not checked).
  [[nodiscard]] Eigen::Vector2d Project(const Eigen::Vector3d& Xc) const {
    return {fx * Xc.x() / Xc.z() + cx, fy * Xc.y() / Xc.z() + cy};
  }
};

// What a reader delivers: images are already undistorted and, for stereo, rectified (or, from
// ApplyCameraRefit, monocular frames carry the lens that undistorts their keypoints: Frame::lens).
struct Calibration {
  Sensor sensor = Sensor::kMonocular;
  PinholeCamera camera;      // left / RGB camera (depth is registered to it)
  double baseline_m = 0;     // stereo: distance between the rectified optical centres
  double frame_rate_hz = 0;  // nominal rate, 0 when unknown
  // Pose of the (rectified) left camera in the body frame whose ground truth is given.
  Eigen::Isometry3d T_body_cam = Eigen::Isometry3d::Identity();
};

// A correction of a monocular dataset's camera model found from its own map (the run's camera
// check, mapping/camera_check.h): the images as the dataset gives them are undistorted by a radial
// k1 at the focal lengths times focal_scale (ApplyCameraRefit, io/orb_settings.h).
struct CameraRefit {
  double focal_scale = 1;
  double k1 = 0;
  [[nodiscard]] bool refined() const { return focal_scale != 1 || k1 != 0; }
  [[nodiscard]] bool operator==(const CameraRefit&) const = default;
};

// The one refinement of the dataset's images that does what `first` and then `second` do, where
// `second` was found on the images `first` gave (its focal lengths those of first's undistorted
// camera). To first order in the products of the k1 values: the scales multiply, k1 = first.k1 *
// second.focal_scale^2 + second.k1 (the neglected term, 3 first.k1 second.k1 r^4 of the radius,
// is 0.1 px at KITTI's image corner for a first k1 of 0.019 and a second of 0.004).
[[nodiscard]] inline CameraRefit ThenRefit(const CameraRefit& first, const CameraRefit& second) {
  return CameraRefit{first.focal_scale * second.focal_scale,
                     first.k1 * second.focal_scale * second.focal_scale + second.k1};
}

}  // namespace flatslam
