// Sensor, frame and trajectory value types shared by readers, renderer, writers and metrics.
// Concurrency: plain values.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>

#include "trajectory/trajectory.h"

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
};

// What a reader delivers: images are already undistorted and, for stereo, rectified.
struct Calibration {
  Sensor sensor = Sensor::kMonocular;
  PinholeCamera camera;      // left / RGB camera (depth is registered to it)
  double baseline_m = 0;     // stereo: distance between the rectified optical centres
  double frame_rate_hz = 0;  // nominal rate, 0 when unknown
  // Pose of the (rectified) left camera in the body frame whose ground truth is given.
  Eigen::Isometry3d T_body_cam = Eigen::Isometry3d::Identity();
};

// One input frame. left is CV_8UC1 (gray); right is CV_8UC1 for stereo;
// depth is CV_32FC1 in metres (0 = no measurement) for RGB-D.
struct Frame {
  size_t index = 0;
  int64_t t_ns = 0;
  cv::Mat left;
  cv::Mat right;
  cv::Mat depth;
};

}  // namespace flatslam
