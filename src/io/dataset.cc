#include "io/dataset.h"

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <system_error>

#include <opencv2/core.hpp>

#include "core/error.h"
#include "io/euroc.h"
#include "io/image_folder.h"
#include "io/image_io.h"
#include "io/kitti.h"
#include "io/orb_settings.h"
#include "io/tum.h"

namespace flatslam {

// Defined by the synthetic renderer (io/synthetic.h); declared here so layout detection
// does not depend on that header.
std::unique_ptr<Dataset> OpenSyntheticDataset(const std::string& scene, const DatasetOptions& options);

void CheckFrame(const Frame& frame, const Calibration& calibration) {
  const cv::Size size(calibration.camera.width, calibration.camera.height);
  auto check = [&](const cv::Mat& image, int type, const char* what) {
    FLATSLAM_CHECK(!image.empty(), "frame ", frame.index, ": no ", what, " image");
    FLATSLAM_CHECK(image.size() == size, "frame ", frame.index, ": ", what, " image is ", image.cols, "x", image.rows,
                   ", the camera's ", size.width, "x", size.height);
    FLATSLAM_CHECK(image.type() == type, "frame ", frame.index, ": ", what, " image has pixel type ",
                   cv::typeToString(image.type()), ", expected ", cv::typeToString(type));
  };
  check(frame.left, CV_8UC1, "left");
  if (calibration.sensor == Sensor::kStereo) check(frame.right, CV_8UC1, "right");
  if (calibration.sensor == Sensor::kRgbd) check(frame.depth, CV_32FC1, "depth");
}

const char* SensorName(Sensor sensor) {
  switch (sensor) {
    case Sensor::kMonocular:
      return "mono";
    case Sensor::kStereo:
      return "stereo";
    case Sensor::kRgbd:
      return "rgbd";
  }
  return "unknown";
}

Sensor ParseSensor(const std::string& name) {
  std::string lower = name;
  std::transform(lower.begin(), lower.end(), lower.begin(), [](unsigned char c) { return std::tolower(c); });
  if (lower == "mono" || lower == "monocular") return Sensor::kMonocular;
  if (lower == "stereo") return Sensor::kStereo;
  if (lower == "rgbd" || lower == "rgb-d") return Sensor::kRgbd;
  Fail("unknown sensor '", name, "': expected mono, stereo or rgbd");
}

DatasetLayout DetectDatasetLayout(const std::string& spec, bool have_settings) {
  if (spec.rfind("synth:", 0) == 0) return DatasetLayout::kSynthetic;
  const std::filesystem::path path(spec);
  std::error_code ec;
  FLATSLAM_CHECK(!spec.empty(), "empty dataset spec: expected synth:NAME or a dataset folder");
  FLATSLAM_CHECK(std::filesystem::is_directory(path, ec), "dataset folder not found: ", spec);
  if (std::filesystem::is_directory(path / "mav0", ec) || io::FolderName(path) == "mav0") return DatasetLayout::kEuroc;
  if (std::filesystem::is_regular_file(path / "rgb.txt", ec)) return DatasetLayout::kTum;
  // With settings, image_0/ without calib.txt is a plain folder of stereo (image_0/ + image_1/) images.
  if (std::filesystem::is_directory(path / "image_0", ec) &&
      (!have_settings || std::filesystem::is_regular_file(path / "calib.txt", ec))) {
    return DatasetLayout::kKitti;
  }
  if (have_settings) return DatasetLayout::kImageFolder;
  FLATSLAM_CHECK(!LooksLikeImageFolder(path), "dataset folder ", spec,
                 " is a plain image folder (not a KITTI, EuRoC or TUM sequence): reading it needs a camera "
                 "settings file (--settings FILE, an ORB-SLAM2/3 YAML with the camera's fx, fy, cx, cy)");
  Fail("cannot tell the layout of dataset folder ", spec,
       ": expected a KITTI sequence (image_0/, calib.txt, times.txt), an EuRoC sequence (mav0/), "
       "a TUM RGB-D sequence (rgb.txt), synth:NAME, or a folder of images with a settings file (--settings)");
}

std::unique_ptr<Dataset> OpenDataset(const std::string& spec, const DatasetOptions& options) {
  const OrbSettings* settings = options.settings.get();
  const std::filesystem::path path(spec);
  std::unique_ptr<Dataset> dataset;
  switch (DetectDatasetLayout(spec, settings != nullptr)) {
    case DatasetLayout::kSynthetic:
      FLATSLAM_CHECK(!settings, "a settings file does not apply to ", spec,
                     ": a synthetic scene renders with its own camera (set width, height, fx in the spec)");
      return OpenSyntheticDataset(spec.substr(std::string_view("synth:").size()), options);
    case DatasetLayout::kEuroc: {
      EurocOptions euroc;
      euroc.sensor = options.sensor;
      euroc.undistort = !settings;
      dataset = std::make_unique<EurocDataset>(path, euroc);
      break;
    }
    case DatasetLayout::kTum: {
      TumOptions tum;
      tum.sensor = options.sensor;
      if (settings) {
        tum.camera = settings->raw_camera();
        tum.depth_factor = settings->depth_map_factor;
        tum.color_order = settings->rgb ? ColorOrder::kRgb : ColorOrder::kBgr;
      }
      dataset = std::make_unique<TumDataset>(path, tum);
      break;
    }
    case DatasetLayout::kKitti: {
      KittiOptions kitti;
      kitti.sensor = options.sensor;
      dataset = std::make_unique<KittiDataset>(path, kitti);
      break;
    }
    case DatasetLayout::kImageFolder: {
      ImageFolderOptions folder;
      folder.sensor = options.sensor;
      folder.camera = settings->raw_camera();
      folder.baseline_m = settings->baseline_m;
      folder.frame_rate_hz = settings->frame_rate_hz;
      if (settings->depth_map_factor > 0) folder.depth_factor = settings->depth_map_factor;
      folder.color_order = settings->rgb ? ColorOrder::kRgb : ColorOrder::kBgr;
      dataset = std::make_unique<ImageFolderDataset>(path, folder);
      break;
    }
  }
  return settings ? ApplyOrbSettings(std::move(dataset), options.settings) : std::move(dataset);
}

}  // namespace flatslam
