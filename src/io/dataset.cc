#include "io/dataset.h"

#include <algorithm>
#include <cctype>
#include <filesystem>
#include <system_error>

#include "core/error.h"
#include "io/euroc.h"
#include "io/image_io.h"
#include "io/kitti.h"
#include "io/tum.h"

namespace flatslam {

// Defined by the synthetic renderer (io/synthetic.h); declared here so layout detection
// does not depend on that header.
std::unique_ptr<Dataset> OpenSyntheticDataset(const std::string& scene, const DatasetOptions& options);

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

std::unique_ptr<Dataset> OpenDataset(const std::string& spec, const DatasetOptions& options) {
  constexpr std::string_view kSynth = "synth:";
  if (spec.rfind(kSynth, 0) == 0) return OpenSyntheticDataset(spec.substr(kSynth.size()), options);

  const std::filesystem::path path(spec);
  std::error_code ec;
  FLATSLAM_CHECK(!spec.empty(), "empty dataset spec: expected synth:NAME or a dataset folder");
  FLATSLAM_CHECK(std::filesystem::is_directory(path, ec), "dataset folder not found: ", spec);

  if (std::filesystem::is_directory(path / "mav0", ec) || io::FolderName(path) == "mav0") {
    EurocOptions euroc;
    euroc.sensor = options.sensor;
    return std::make_unique<EurocDataset>(path, euroc);
  }
  if (std::filesystem::is_regular_file(path / "rgb.txt", ec)) {
    TumOptions tum;
    tum.sensor = options.sensor;
    return std::make_unique<TumDataset>(path, tum);
  }
  if (std::filesystem::is_directory(path / "image_0", ec)) {
    KittiOptions kitti;
    kitti.sensor = options.sensor;
    return std::make_unique<KittiDataset>(path, kitti);
  }
  Fail("cannot tell the layout of dataset folder ", spec,
       ": expected a KITTI sequence (image_0/, calib.txt, times.txt), an EuRoC sequence (mav0/), "
       "a TUM RGB-D sequence (rgb.txt) or synth:NAME");
}

}  // namespace flatslam
