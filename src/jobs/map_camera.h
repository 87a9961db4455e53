// A monocular session run with the camera another session's saved map used (`--camera-from`):
// sessions of one camera then share it, and their maps merge.
// Concurrency: free functions; they read the snapshot file and nothing else.
#pragma once

#include <filesystem>
#include <memory>

#include "io/calibration.h"
#include "io/dataset.h"

namespace flatslam {

// The calibrations describe one camera (sensor, size, intrinsics to a millionth of the focal
// length, baseline): a map built through `have` continues, merges or shares its camera with a
// session through `want`.
[[nodiscard]] bool SameCamera(const Calibration& have, const Calibration& want);

// The dataset seen through the camera the map at `map` was built with: the refinement its
// session made of the dataset's camera (SnapshotMetadata::camera_refit) applied to this dataset,
// which must then give the map's calibration. *refit (may be null) receives that refinement
// (refined() false: the map's session used the camera as given). Throws flatslam::Error naming
// the file when the dataset is not monocular, the file is no snapshot, or the camera differs.
[[nodiscard]] std::unique_ptr<Dataset> DatasetThroughCameraOf(std::unique_ptr<Dataset> dataset,
                                                               const std::filesystem::path& map, CameraRefit* refit);

}  // namespace flatslam
