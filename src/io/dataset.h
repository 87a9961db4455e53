// One interface for every frame source: KITTI, EuRoC, TUM RGB-D and the synthetic renderer.
// Concurrency: read() is const and may be called from several threads at once.
#pragma once

#include <memory>
#include <optional>
#include <string>

#include "io/types.h"

namespace flatslam {

class Dataset {
 public:
  virtual ~Dataset() = default;

  // Short human-readable description, e.g. "KITTI 07 (mono)".
  [[nodiscard]] virtual std::string name() const = 0;
  [[nodiscard]] virtual const Calibration& calibration() const = 0;
  [[nodiscard]] virtual size_t size() const = 0;
  // Loads (or renders) frame i. Throws flatslam::Error naming the file on a missing,
  // unreadable or wrongly sized image.
  [[nodiscard]] virtual Frame read(size_t i) const = 0;
  // Ground truth of the left camera (T_world_cam) at the frame timestamps when known.
  [[nodiscard]] virtual std::optional<Trajectory> ground_truth() const = 0;
};

// Checks that a frame fits the calibration: a CV_8UC1 left image of the camera's size, a right
// image like it for stereo, a CV_32FC1 depth image of the same size for RGB-D. Throws
// flatslam::Error naming the frame and what is wrong (readers already name the file).
void CheckFrame(const Frame& frame, const Calibration& calibration);

struct OrbSettings;  // io/orb_settings.h

struct DatasetOptions {
  // Requested sensor; empty = the richest the dataset offers (stereo/RGB-D over mono).
  std::optional<Sensor> sensor;
  // Synthetic scenes only: seed of the renderer's noise.
  uint64_t seed = 1;
  // Camera settings (an ORB-SLAM2/3 file, see io/orb_settings.h) replacing the dataset's calibration,
  // with their depth factor and colour order; needed for a plain image folder. Null = the dataset's own.
  std::shared_ptr<const OrbSettings> settings;
};

enum class DatasetLayout { kSynthetic, kKitti, kEuroc, kTum, kImageFolder };

// The layout OpenDataset reads `spec` as (first match wins):
//   synth:NAME                   synthetic scene (see SyntheticSceneNames())
//   .../<seq> with mav0/         EuRoC ASL
//   .../<seq> with rgb.txt       TUM RGB-D
//   .../sequences/NN             KITTI odometry sequence, image_0/ (poses from ../../poses/NN.txt;
//                                with settings, only when calib.txt is there too)
//   any other folder             plain image folder (io/image_folder.h), only with settings
// Throws flatslam::Error naming what is missing (a settings file, for a folder of images).
[[nodiscard]] DatasetLayout DetectDatasetLayout(const std::string& spec, bool have_settings);

// Opens a dataset from a path or spec, detecting its layout as above; with settings, the images
// are read raw and ApplyOrbSettings gives them the settings' calibration. Throws flatslam::Error
// naming what is missing.
[[nodiscard]] std::unique_ptr<Dataset> OpenDataset(const std::string& spec, const DatasetOptions& options = {});

}  // namespace flatslam
