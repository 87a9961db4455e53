// ORB-SLAM2 / ORB-SLAM3 camera settings files (OpenCV FileStorage YAML starting "%YAML:1.0"), so a
// user's own camera, or a dataset with a calibration of its own, runs with the file they already have.
//
// Keys read (ORB-SLAM3 files say File.version: "1.0"; both spellings may be mixed if they agree):
//   camera       Camera.fx/fy/cx/cy (ORB-SLAM2) or Camera1.fx/fy/cx/cy; Camera.width/height (optional:
//                the images' size); Camera.type PinHole or Rectified (KannalaBrandt8 is rejected)
//   distortion   Camera.k1/k2/p1/p2/k3 or Camera1.*: radial-tangential; the images are undistorted
//   stereo       baseline from Camera.bf / fx, Stereo.b, Stereo.T_c1_c2 (right camera in the left's frame)
//                or RIGHT.P; unrectified pairs from ORB-SLAM2's LEFT/RIGHT.{width,height,K,D,R,P}
//                blocks (rectified with R and P) or ORB-SLAM3's Camera2.* + Stereo.T_c1_c2
//                (rectified with cv::stereoRectify)
//   other        Camera.fps, Camera.RGB (0 BGR, 1 RGB), DepthMapFactor / RGBD.DepthMapFactor,
//                ThDepth / Stereo.ThDepth, ORBextractor.nFeatures/scaleFactor/nLevels/iniThFAST/minThFAST
//   ignored      Viewer.*, IMU.*, System.*, Tbc, Camera.bFishEye 0, Camera.imageScale 1,
//                Camera.newWidth/newHeight equal to the size
// Any other key, two keys that disagree, a missing or non-positive focal length, a fisheye model,
// resizing and distortion on an already rectified stereo pair are errors naming the keys and the file.
// Concurrency: plain values and stateless functions; the dataset ApplyOrbSettings returns is const
// and thread-safe for read().
#pragma once

#include <array>
#include <filesystem>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>
#include <opencv2/core/matx.hpp>

#include "io/dataset.h"
#include "io/types.h"

namespace flatslam {

// A raw pinhole camera with radial-tangential distortion, as a settings file gives it.
struct SettingsCamera {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  std::array<double, 5> distortion{};  // k1, k2, p1, p2, k3 (OpenCV order)

  [[nodiscard]] cv::Matx33d K() const { return {fx, 0, cx, 0, fy, cy, 0, 0, 1}; }
  [[nodiscard]] cv::Mat distortion_mat() const;  // 1 x 5, CV_64F
  [[nodiscard]] bool distorted() const;
};

// One of ORB-SLAM2's LEFT.* / RIGHT.* blocks: the raw camera K, D of size width x height, and
// the rectification: rotation R (x_rect = R x_raw) and rectified projection P.
struct RectificationBlock {
  cv::Size size;
  cv::Matx33d K;
  cv::Mat D;  // 1 x 4 or 1 x 5, CV_64F
  cv::Matx33d R;
  cv::Matx34d P;
};

struct OrbSettings {
  std::filesystem::path file;
  int orb_slam_version = 2;  // 3 when File.version is "1.0"
  // The (left) camera: Camera.* or Camera1.*. With LEFT/RIGHT blocks it is LEFT.P, the rectified one.
  SettingsCamera camera;
  cv::Size size;  // Camera.width x Camera.height (LEFT.width x height); 0 x 0 = the images' size
  // ORB-SLAM3 PinHole stereo: Camera2.* and Stereo.T_c1_c2, rectified by flatslam.
  std::optional<SettingsCamera> right_camera;
  std::optional<Eigen::Isometry3d> T_left_right;  // Stereo.T_c1_c2: maps right-camera coordinates to the left
  // ORB-SLAM2 rectification blocks (both or neither).
  std::optional<RectificationBlock> left_block, right_block;
  double baseline_m = 0;        // of the rectified pair, or the RGB-D virtual baseline (Camera.bf / fx); 0 = none
  double frame_rate_hz = 0;     // Camera.fps; 0 = the dataset's
  bool rgb = false;             // Camera.RGB: colour images are RGB (true) or BGR (false)
  double depth_map_factor = 0;  // raw depth units per metre; 0 = the dataset's
  // SLAM options by name (config/slam_config.h): orb.features, orb.scale_factor, orb.levels,
  // orb.fast_threshold, orb.min_fast_threshold, close_depth_baselines; in file order.
  std::vector<std::pair<std::string, std::string>> slam_options;

  // The camera the stored images are taken with (LEFT.K / the left camera) and their size.
  [[nodiscard]] PinholeCamera raw_camera() const;
};

// Reads and checks a settings file. Throws flatslam::Error naming the file and the offending keys.
[[nodiscard]] OrbSettings ReadOrbSettings(const std::filesystem::path& path);

// slam_options plus what depends on the sensor: for RGB-D, the baseline as rgbd_virtual_baseline_m
// (ORB-SLAM's Camera.bf for RGB-D is that virtual baseline times fx).
[[nodiscard]] std::vector<std::pair<std::string, std::string>> SettingsSlamOptions(const OrbSettings& settings,
                                                                                   Sensor sensor);

// The dataset `raw` (which delivers raw, not undistorted images) seen through `settings`: their
// camera, baseline and frame rate replace its calibration; images (and depth, nearest-neighbour)
// are undistorted or rectified as the settings say; T_body_cam and ground truth follow the
// rectified left camera. Throws naming the file when the image size differs from the settings'
// or a stereo dataset gets no baseline.
[[nodiscard]] std::unique_ptr<Dataset> ApplyOrbSettings(std::unique_ptr<Dataset> raw,
                                                        std::shared_ptr<const OrbSettings> settings);

// The dataset seen through a refined camera: the lens of its camera at its focal lengths times
// refit.focal_scale (principal point kept) with radial refit.k1, undistorted to the camera that
// keeps only valid pixels. Its calibration is that undistorted camera's; its images pass as
// given, each frame carrying the lens (Frame::lens) that takes its keypoints into that camera.
// A monocular dataset only (throws naming the dataset otherwise).
[[nodiscard]] std::unique_ptr<Dataset> ApplyCameraRefit(std::unique_ptr<Dataset> dataset, const CameraRefit& refit);

// One refinement of a given camera as ApplyCameraRefit applies it: the camera of the images it
// gives, and where their pixels lie in the given images. Two refinements of one camera see the
// same given image, so a keypoint measured through one is re-expressed in the other through it.
class RefinedCamera {
 public:
  RefinedCamera(const PinholeCamera& given, const CameraRefit& refit);

  // The camera of the refined images (ApplyCameraRefit's calibration).
  [[nodiscard]] const PinholeCamera& camera() const { return camera_; }
  // Pixels of the refined image in the given image, and back (the inverse of the distortion by
  // fixed-point iteration, until it reproduces the given pixel to 1e-12 px or for 50 steps).
  [[nodiscard]] std::vector<Eigen::Vector2d> ToGiven(std::span<const Eigen::Vector2d> p) const;
  [[nodiscard]] std::vector<Eigen::Vector2d> FromGiven(std::span<const Eigen::Vector2d> q) const;

 private:
  SettingsCamera lens_;   // the given camera at the refined focal lengths, with the refined k1
  PinholeCamera camera_;  // the undistorted camera
};

// ApplyCameraRefit with the lens given, a RefinedCamera of the dataset's own camera, which its
// frames then share (for a caller that keeps the lens too).
[[nodiscard]] std::unique_ptr<Dataset> ApplyCameraRefit(std::unique_ptr<Dataset> dataset,
                                                        std::shared_ptr<const RefinedCamera> lens);

// Pixels of the images of refinement `from` in those of refinement `to` of the same given camera.
[[nodiscard]] std::vector<Eigen::Vector2d> Reexpress(const RefinedCamera& from, const RefinedCamera& to,
                                                     std::span<const Eigen::Vector2d> p);

}  // namespace flatslam
