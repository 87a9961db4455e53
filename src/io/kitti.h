// KITTI odometry reader: sequences/NN/{image_0,image_1}/%06d.png, calib.txt (P0..P3),
// times.txt, ground truth ../../poses/NN.txt (T_world_cam0, world = cam0 at frame 0).
// Images are already rectified; the image size comes from the first left image.
// Concurrency: read() is const and thread-safe.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "io/dataset.h"
#include "io/types.h"

namespace flatslam {

struct KittiOptions {
  // Requested sensor; empty = stereo when image_1/ exists, else monocular. RGB-D is an error.
  std::optional<Sensor> sensor;
  // Ground-truth file; empty = <sequence>/../../poses/NN.txt when it exists.
  std::filesystem::path poses_file;
};

class KittiDataset final : public Dataset {
 public:
  // sequence_dir: .../sequences/NN. Throws flatslam::Error naming the missing or malformed
  // file (calib.txt, times.txt, the first/last image, the poses file).
  explicit KittiDataset(const std::filesystem::path& sequence_dir, const KittiOptions& options = {});

  [[nodiscard]] std::string name() const override;
  [[nodiscard]] const Calibration& calibration() const override { return calibration_; }
  [[nodiscard]] size_t size() const override { return times_ns_.size(); }
  [[nodiscard]] Frame read(size_t i) const override;
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return ground_truth_; }

  // Path of image `camera` (0 = left, 1 = right) of frame i.
  [[nodiscard]] std::filesystem::path image_path(int camera, size_t i) const;

 private:
  std::filesystem::path dir_;
  std::string sequence_;
  Calibration calibration_;
  std::vector<int64_t> times_ns_;
  std::optional<Trajectory> ground_truth_;
};

}  // namespace flatslam
