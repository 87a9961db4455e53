// EuRoC MAV (ASL layout) reader: mav0/cam0[,cam1]/{data.csv,data/,sensor.yaml}. Images are
// undistorted (mono) or undistorted and stereo-rectified (cv::stereoRectify, zero disparity
// at infinity) with maps computed once; ground truth is the body pose from
// mav0/state_groundtruth_estimate0/data.csv, else <seq>/groundtruth_tum.txt, moved to the
// rectified left camera with Calibration::T_body_cam.
// Concurrency: read() is const and thread-safe (the maps are read-only after construction).
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <opencv2/core/matx.hpp>

#include "io/dataset.h"
#include "io/rectify.h"
#include "io/types.h"

namespace flatslam {

// One mav0/camN/sensor.yaml: pinhole with radial-tangential distortion (k1 k2 p1 p2).
struct EurocCameraModel {
  cv::Matx33d K = cv::Matx33d::eye();
  cv::Vec4d distortion;  // k1, k2, p1, p2
  cv::Size resolution;
  double rate_hz = 0;
  Eigen::Isometry3d T_body_sensor = Eigen::Isometry3d::Identity();  // sensor.yaml T_BS
};

// Parses the fields above from a sensor.yaml (a small tolerant YAML subset reader: OpenCV's
// FileStorage rejects these files, which lack the %YAML header). Throws naming the file
// and the missing or malformed field; other camera or distortion models are an error.
[[nodiscard]] EurocCameraModel ReadEurocSensorYaml(const std::filesystem::path& path);

struct EurocOptions {
  // Requested sensor; empty = stereo when mav0/cam1 exists, else monocular. RGB-D is an error.
  std::optional<Sensor> sensor;
  // Free scaling of the undistorted/rectified image: 0 keeps only valid pixels (no black
  // border, larger focal length), 1 keeps every source pixel.
  double rectify_alpha = 0;
  // cam0 and cam1 frames pair when their stamps differ by at most this (EuRoC: identical).
  int64_t max_stereo_dt_ns = 2'500'000;
  // false: deliver the raw (distorted) images with cam0's raw K as the camera, for a settings file
  // that undistorts and rectifies them itself (io/orb_settings.h).
  bool undistort = true;

  [[nodiscard]] bool Check() const { return rectify_alpha >= 0 && rectify_alpha <= 1 && max_stereo_dt_ns >= 0; }
};

class EurocDataset final : public Dataset {
 public:
  // sequence_dir: the folder holding mav0/ (or mav0/ itself). Throws flatslam::Error naming
  // the missing or malformed file.
  explicit EurocDataset(const std::filesystem::path& sequence_dir, const EurocOptions& options = {});

  [[nodiscard]] std::string name() const override;
  [[nodiscard]] const Calibration& calibration() const override { return calibration_; }
  [[nodiscard]] size_t size() const override { return frames_.size(); }
  [[nodiscard]] Frame read(size_t i) const override;
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return ground_truth_; }

  // Raw (distorted) model of camera 0 or 1 as read from sensor.yaml.
  [[nodiscard]] const EurocCameraModel& raw_camera(int camera) const { return raw_.at(camera); }
  // Rotation taking raw camera `camera` coordinates to its rectified frame (identity for mono and raw).
  [[nodiscard]] const cv::Matx33d& rectification_rotation(int camera) const { return rotation_.at(camera); }
  // 3x4 projection of the rectified camera `camera` (from stereoRectify; P[0][3] = -fx * baseline);
  // the raw K with a zero last column when not undistorting.
  [[nodiscard]] const cv::Matx34d& rectified_projection(int camera) const { return projection_.at(camera); }
  // Stereo: cam0 plus cam1 frames without a partner within max_stereo_dt_ns (dropped).
  [[nodiscard]] size_t unmatched_dropped() const { return unmatched_; }
  // File the ground truth came from; empty when there is none.
  [[nodiscard]] const std::filesystem::path& ground_truth_file() const { return ground_truth_file_; }

 private:
  struct Entry {
    int64_t t_ns = 0;  // cam0 stamp
    std::filesystem::path left, right;
  };

  std::filesystem::path dir_;  // holds mav0/
  Calibration calibration_;
  std::vector<EurocCameraModel> raw_;
  std::vector<cv::Matx33d> rotation_;
  std::vector<cv::Matx34d> projection_;
  std::vector<RectifyMap> maps_;  // per camera; empty maps when not undistorting
  std::vector<Entry> frames_;
  size_t unmatched_ = 0;
  std::filesystem::path ground_truth_file_;
  std::optional<Trajectory> ground_truth_;
};

}  // namespace flatslam
