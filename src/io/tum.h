// TUM RGB-D reader: rgb.txt / depth.txt / groundtruth.txt, RGB-depth association as in
// TUM's associate.py, 16-bit depth PNGs in metres. Also the TUM pose-file helpers the EuRoC
// reader shares (its groundtruth_tum.txt fallback).
// Concurrency: read() is const and thread-safe; the free functions are stateless.
//
// Calibration, first found wins (TumOptions::camera, from a settings file, comes before all):
//   1. camera.txt in the sequence folder (written by flatslam's dataset writer), one line:
//        fx fy cx cy width height [depth_factor]
//      '#' starts a comment line; depth_factor defaults to 5000.
//   2. the published Freiburg calibration, chosen by a "freiburg1/2/3" (or "fr1/2/3") token
//      in the folder name, 640x480, depth factor 5000. fr1/fr2 images are distorted
//      (k1 ~ 0.26 / 0.23): read() undistorts the colour and the depth image with the same map
//      (depth nearest-neighbour), and the calibration is the undistorted camera's (only valid
//      pixels: a larger focal length). fr3's images come undistorted.
//   3. otherwise an error naming the missing camera.txt.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "io/dataset.h"
#include "io/image_io.h"
#include "io/rectify.h"
#include "io/types.h"

namespace flatslam {

struct TumOptions {
  // Requested sensor; empty = RGB-D when depth.txt exists, else monocular. Stereo is an error.
  std::optional<Sensor> sensor;
  // RGB and depth stamps pair when |t_rgb - t_depth| < this (associate.py's 0.02 s).
  int64_t max_association_dt_ns = 20'000'000;
  // Camera given by the caller (a settings file), used instead of camera.txt or the Freiburg
  // intrinsics; width and height 0 = the size of the first RGB image.
  std::optional<PinholeCamera> camera;
  // Raw depth units per metre; 0 = camera.txt's factor, else 5000.
  double depth_factor = 0;
  ColorOrder color_order = ColorOrder::kBgr;  // of colour RGB images

  [[nodiscard]] bool Check() const { return max_association_dt_ns > 0 && depth_factor >= 0; }
};

// Contents of camera.txt.
struct TumCameraFile {
  PinholeCamera camera;
  double depth_factor = 5000;  // raw 16-bit depth units per metre
};

// Reads camera.txt (format above); throws naming the file and line on anything malformed.
[[nodiscard]] TumCameraFile ReadTumCameraFile(const std::filesystem::path& path);
// Writes camera.txt (format above) with a comment header; throws naming the file on failure.
void WriteTumCameraFile(const std::filesystem::path& path, const TumCameraFile& file);

class TumDataset final : public Dataset {
 public:
  // Throws flatslam::Error naming the missing or malformed file.
  explicit TumDataset(const std::filesystem::path& sequence_dir, const TumOptions& options = {});

  [[nodiscard]] std::string name() const override;
  [[nodiscard]] const Calibration& calibration() const override { return calibration_; }
  [[nodiscard]] size_t size() const override { return frames_.size(); }
  [[nodiscard]] Frame read(size_t i) const override;
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return ground_truth_; }

  // RGB-D: RGB frames left without a depth partner (dropped). 0 for monocular.
  [[nodiscard]] size_t unmatched_rgb() const { return unmatched_rgb_; }
  [[nodiscard]] double depth_factor() const { return depth_factor_; }
  // "camera.txt", "Freiburg intrinsics" (fr3), "Freiburg intrinsics and distortion" (fr1, fr2)
  // or "options".
  [[nodiscard]] const std::string& calibration_source() const { return calibration_source_; }
  // Timestamp of the depth image paired with frame i (RGB-D only).
  [[nodiscard]] int64_t depth_t_ns(size_t i) const { return frames_.at(i).depth_t_ns; }

 private:
  struct Entry {
    int64_t t_ns = 0;  // RGB stamp
    std::filesystem::path rgb;
    int64_t depth_t_ns = 0;
    std::filesystem::path depth;
  };

  std::filesystem::path dir_;
  std::string calibration_source_;
  Calibration calibration_;
  double depth_factor_ = 5000;
  ColorOrder color_order_ = ColorOrder::kBgr;
  std::vector<Entry> frames_;
  size_t unmatched_rgb_ = 0;
  std::optional<Trajectory> ground_truth_;
  RectifyMap undistort_;  // fr1/fr2 without camera.txt; empty: images pass unchanged
};

namespace io {

// Reads a TUM pose file ("t tx ty tz qx qy qz qw", '#' comments), sorted by time.
// Quaternions are normalized; errors name the file and line.
[[nodiscard]] Trajectory ReadTumPoseFile(const std::filesystem::path& path);

// How ground truth at a higher or different rate is sampled at frame timestamps.
struct PoseSamplingOptions {
  // Interpolate (lerp + slerp) between neighbours at most this far apart.
  int64_t max_interpolation_gap_ns = 100'000'000;
  // Otherwise (edges, gaps) take the nearest sample if it is at most this far.
  int64_t max_nearest_dt_ns = 20'000'000;
};

// Poses of sorted `samples` at each of `t_ns`; stamps that cannot be sampled are left out
// (the result keeps the query order and stamps).
[[nodiscard]] Trajectory PosesAtTimes(const Trajectory& samples, const std::vector<int64_t>& t_ns,
                                      const PoseSamplingOptions& options = {});

// Pairs two sorted stamp lists like TUM's associate.py: all pairs with |a - b| < max_dt,
// greedily by increasing |a - b|, each element used at most once. Result sorted by a.
[[nodiscard]] std::vector<std::pair<size_t, size_t>> AssociateStamps(const std::vector<int64_t>& a,
                                                                     const std::vector<int64_t>& b, int64_t max_dt_ns);

}  // namespace io
}  // namespace flatslam
