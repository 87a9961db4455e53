// How well a map's camera model fits its own keypoints: the map's keyframe poses and points are
// adjusted once more with two camera parameters free, a common scale of the focal lengths and a
// radial term k1 of the undistorted images (x_d = x (1 + k1 r^2) on normalized coordinates, as
// OpenCV's and ORB-SLAM's k1), and the result is reported with its standard errors. A monocular
// map's scale through turns follows small errors of the camera model (docs/STATUS.md: 2% of
// focal length moves it about 4% per 90-degree turn), so a calibration the data disagrees with is
// worth knowing; whether the data can tell depends on the motion (a straight road barely fixes
// the focal length), which the standard errors say.
// Concurrency: reads the map (copies what it adjusts); the caller keeps writers out while it runs.
#pragma once

#include <cstddef>
#include <string>

#include "ecs/map.h"
#include "geometry/camera.h"

namespace flatslam {

struct CameraCheckOptions {
  size_t min_observations = 2;   // keyframes that see a point, for it to enter
  double min_ray_angle_deg = 1;  // and the widest angle between their rays
  int max_iterations = 50;
  double pixel_sigma = 1;  // keypoint noise at level 0, pixels (grows with the level's scale)
  // At most this many of the points that qualify enter, an even share of them in id order
  // (0 = all): the standard errors grow as one over the root of the observations, the time
  // about linearly, so a check run during a session bounds its cost this way.
  size_t max_points = 0;
};

// Observations a check needs before it says anything.
inline constexpr size_t kCameraCheckMinObservations = 1000;

struct CameraCheck {
  bool ok = false;             // kCameraCheckMinObservations or more, and the solve converged
  double focal_scale = 1;      // refined fx / given fx (fy scales with it)
  double focal_scale_sigma = 0;
  double k1 = 0;               // radial term on top of the given (undistorted) model
  double k1_sigma = 0;
  double rmse_before_px = 0;   // per-coordinate RMS reprojection error at level 0, inliers
  double rmse_after_px = 0;
  size_t observations = 0;
  size_t keyframes = 0;
  size_t points = 0;
};

// Adjusts a copy of the map's keyframes (the first two by id held: the gauge and, for a monocular
// map, the scale; those with under 10 observations held too, and beyond 120 free keyframes those
// with the fewest observations) and points seen by options.min_observations keyframes with rays
// options.min_ray_angle_deg apart, with the focal scale and k1 free, robustly (Huber at the 95%
// chi-square of 2 degrees of freedom, Levenberg-Marquardt over the normal equations reduced to
// the poses and the two parameters); left-image observations only. Single-threaded, and the same
// bits on every run. ok = false on a map too small to say.
[[nodiscard]] CameraCheck CheckCameraModel(const Map& map, const CameraGeometry& geometry,
                                           const CameraCheckOptions& options = {});

// How many standard errors from the given model a map must put either parameter to disagree
// with it: beyond what a well-fitted map's own noise reaches (the exact camera's maps in
// docs/STATUS.md stay within 2.2).
inline constexpr double kCameraCheckDisagreeSigmas = 5;

// The map's keypoints disagree with the camera model (check.ok and either parameter beyond
// kCameraCheckDisagreeSigmas standard errors).
[[nodiscard]] bool CameraCheckDisagrees(const CameraCheck& check);

// How far, in pixels, the refined model moves the point at the image's farthest corner from where
// the given one puts it: what the disagreement means on the image.
[[nodiscard]] double CameraCheckCornerShiftPx(const CameraCheck& check, const PinholeCamera& camera);

// Lines for a user: the refined focal length and k1 with their standard errors and how many
// standard errors they sit from the given model; whether the map's keypoints disagree with it
// (either beyond 5 standard errors) or cannot tell. Empty when !check.ok.
[[nodiscard]] std::string DescribeCameraCheck(const CameraCheck& check, const PinholeCamera& camera);

}  // namespace flatslam
