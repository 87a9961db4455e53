// COLMAP text models from flatslam maps: cameras.txt, images.txt and points3D.txt in the layout of
// COLMAP's documented text format, so that COLMAP (model_analyzer, model_converter, the GUI, MVS)
// and tools that read COLMAP models can use a flatslam map as a sparse reconstruction.
// Concurrency: reads the map (and the snapshot) without changing them, so the caller must keep
// writers away meanwhile (one writer or many readers); writes only the files under the given
// directory; reentrant for distinct directories.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <vector>

#include "ecs/map.h"
#include "io/calibration.h"
#include "storage/snapshot.h"

namespace flatslam {

// What one export wrote; the numbers COLMAP's model_analyzer reports for the model.
struct ColmapExportCounts {
  size_t images = 0;           // keyframes ("Registered images")
  size_t points = 0;           // map points with at least one observation ("Points")
  size_t observations = 0;     // keypoints bound to an exported point = track entries ("Observations")
  size_t points_left_out = 0;  // map points with fewer observations than the minimum track (at least 1)
  // Mean over the exported points of each point's mean reprojection error in pixels (the ERROR
  // column); observations behind their camera are left out of it.
  double mean_reprojection_error_px = 0;
};

// Writes map as a COLMAP text model into dir (created when missing; each of the three files is
// replaced atomically, anything else in dir is left alone).
//  - cameras.txt: one PINHOLE camera, CAMERA_ID 1, from calibration.camera. flatslam's images are
//    undistorted (and rectified), so no distortion parameters. For stereo and RGB-D only the left
//    (colour) camera exists in the model: keyframes hold that camera's keypoints and poses.
//  - images.txt: one image per keyframe, IMAGE_ID = 1 + the keyframe's position in the arena's
//    dense order (= its index in a snapshot), pose world-to-camera (KeyFrame::T_cam_world), NAME
//    "<t_ns>.png" ("agent<a>/<t_ns>.png" when the map holds several agents; "-kf<id>" is added
//    should a name still repeat). Names label images: no image file is written or expected.
//    POINTS2D are the keyframe's keypoints in order (so POINT2D_IDX = keypoint index), with the
//    id of the map point seen there or -1.
//  - points3D.txt: one point per map point with observations, POINT3D_ID = 1 + its dense index
//    (= its index in a snapshot), colour 128 128 128 (maps hold no colour), ERROR its mean
//    reprojection error, TRACK its observations as (IMAGE_ID, keypoint index).
// Pixel coordinates (keypoints, principal point) get +0.5: COLMAP puts the centre of the first
// pixel at (0.5, 0.5), flatslam (like OpenCV) at (0, 0).
// Throws flatslam::Error naming the path when dir or a file cannot be written, or when the
// camera is not valid.
// min_track: points seen by fewer keyframes are left out (their keypoints get POINT3D_ID -1);
// at least 1. 2 suits COLMAP's bundle_adjuster, which refuses points seen once (a stereo map
// has them: points placed from one keyframe's stereo depth).
ColmapExportCounts WriteColmapModel(const Map& map, const Calibration& calibration, const std::filesystem::path& dir,
                                    size_t min_track = 1);

// One map of a snapshot as exported by WriteColmapModels.
struct ColmapMapExport {
  uint32_t map_id = 0;
  std::filesystem::path dir;
  ColmapExportCounts counts;
};

// Writes every map of the snapshot with its calibration: a snapshot of one map into dir itself,
// one of several maps (a merge that left maps apart) into dir/<map id>/ each, since every map
// has its own frame and its own point ids. Throws flatslam::Error as WriteColmapModel, and for a
// snapshot that holds no map.
std::vector<ColmapMapExport> WriteColmapModels(const LoadedSnapshot& snapshot, const std::filesystem::path& dir,
                                               size_t min_track = 1);

}  // namespace flatslam
