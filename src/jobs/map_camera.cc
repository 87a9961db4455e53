#include "jobs/map_camera.h"

#include <cmath>

#include "core/error.h"
#include "io/orb_settings.h"
#include "storage/snapshot.h"

namespace flatslam {

bool SameCamera(const Calibration& have, const Calibration& want) {
  return have.sensor == want.sensor && have.camera.width == want.camera.width &&
         have.camera.height == want.camera.height && std::abs(have.camera.fx - want.camera.fx) < 1e-6 * want.camera.fx &&
         std::abs(have.camera.fy - want.camera.fy) < 1e-6 * want.camera.fy &&
         std::abs(have.camera.cx - want.camera.cx) < 1e-6 * want.camera.fx &&
         std::abs(have.camera.cy - want.camera.cy) < 1e-6 * want.camera.fy &&
         std::abs(have.baseline_m - want.baseline_m) < 1e-9 + 1e-6 * want.baseline_m;
}

std::unique_ptr<Dataset> DatasetThroughCameraOf(std::unique_ptr<Dataset> dataset, const std::filesystem::path& map,
                                                CameraRefit* refit) {
  FLATSLAM_CHECK(dataset, "DatasetThroughCameraOf: null dataset");
  const Sensor sensor = dataset->calibration().sensor;
  FLATSLAM_CHECK(sensor == Sensor::kMonocular, "camera from ", map.string(), ": only monocular runs refine their camera; ",
                 dataset->name(), " is read as ", sensor == Sensor::kStereo ? "stereo" : "RGB-D");
  Calibration made_with;
  CameraRefit used;
  {
    const MapSnapshotView view = MapSnapshotView::Open(map);
    made_with = view.calibration();
    used = view.camera_refit();
  }
  if (used.refined()) dataset = ApplyCameraRefit(std::move(dataset), used);
  const PinholeCamera& have = made_with.camera;
  const PinholeCamera& want = dataset->calibration().camera;
  FLATSLAM_CHECK(SameCamera(made_with, dataset->calibration()), "camera from ", map.string(),
                 ": its map was made with another camera (", have.width, "x", have.height, ", fx ", have.fx, ") than ",
                 dataset->name(), " gives (", want.width, "x", want.height, ", fx ", want.fx,
                 used.refined() ? " through the map's refinement)" : ")");
  if (refit) *refit = used;
  return dataset;
}

}  // namespace flatslam
