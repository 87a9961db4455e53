// A plain folder of images whose camera comes from elsewhere (a settings file: flatslam run FOLDER
// --settings FILE). Layouts, images being .png, .jpg or .jpeg files:
//   FOLDER/*.png                                   monocular
//   FOLDER/left/ + right/  (or image_0/ + image_1/, or cam0/ + cam1/)   stereo, paired in order
//   FOLDER/rgb/ + depth/                           RGB-D: 16-bit depth PNGs, raw / depth factor = metres
// Paired folders must hold as many images each. Monocular reads the images in FOLDER itself, else
// the left (or rgb/) ones. Images are sorted by file name, numerically when every name is a number.
// Timestamps, first that applies: FOLDER/times.txt (one time in seconds per line, one line per
// frame); the file names when all are numbers (nanoseconds above 1e12, else seconds; names counting
// 0, 1, 2... or 1, 2, 3... are frame numbers: t = n / frame rate); else frame index / frame rate.
// Ground truth: FOLDER/groundtruth.txt (TUM format, poses of the left camera as stored) when present.
// Concurrency: read() is const and thread-safe.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "io/dataset.h"
#include "io/image_io.h"
#include "io/types.h"

namespace flatslam {

struct ImageFolderOptions {
  // Requested sensor; empty = stereo or RGB-D when their subfolders exist, else monocular.
  std::optional<Sensor> sensor;
  PinholeCamera camera;        // of the stored images; width and height 0 = the first image's size
  double baseline_m = 0;       // stereo
  double frame_rate_hz = 0;    // needed when neither times.txt nor the file names give times
  double depth_factor = 5000;  // raw depth units per metre
  ColorOrder color_order = ColorOrder::kBgr;

  [[nodiscard]] bool Check() const { return frame_rate_hz >= 0 && depth_factor > 0 && baseline_m >= 0; }
};

class ImageFolderDataset final : public Dataset {
 public:
  // Throws flatslam::Error naming the folder and what is missing or inconsistent.
  explicit ImageFolderDataset(const std::filesystem::path& dir, const ImageFolderOptions& options);

  [[nodiscard]] std::string name() const override;
  [[nodiscard]] const Calibration& calibration() const override { return calibration_; }
  [[nodiscard]] size_t size() const override { return frames_.size(); }
  [[nodiscard]] Frame read(size_t i) const override;
  [[nodiscard]] std::optional<Trajectory> ground_truth() const override { return ground_truth_; }

  // Where the timestamps came from: "times.txt", "file names", "frame numbers" or "frame rate".
  [[nodiscard]] const std::string& time_source() const { return time_source_; }

 private:
  struct Entry {
    int64_t t_ns = 0;
    std::filesystem::path left, second;  // second: right image or depth image
  };

  std::filesystem::path dir_;
  Calibration calibration_;
  double depth_factor_ = 5000;
  ColorOrder color_order_ = ColorOrder::kBgr;
  std::vector<Entry> frames_;
  std::string time_source_;
  std::optional<Trajectory> ground_truth_;
};

// True when `dir` holds images or one of the subfolders above (to tell a user who forgot the
// settings file what is missing).
[[nodiscard]] bool LooksLikeImageFolder(const std::filesystem::path& dir);

}  // namespace flatslam
