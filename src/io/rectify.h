// Undistortion and stereo rectification of raw images (radial-tangential distortion, OpenCV's
// k1 k2 p1 p2 [k3]) with maps computed once; shared by the EuRoC reader and ORB-SLAM settings files.
// Concurrency: a RectifyMap is immutable after construction, Apply() is const and thread-safe;
// the free functions are stateless.
#pragma once

#include <Eigen/Geometry>
#include <opencv2/core/mat.hpp>
#include <opencv2/core/matx.hpp>

namespace flatslam {

// How Apply() samples the raw image: linear for intensities, nearest for depth (never blends
// the depths of two surfaces at an edge).
enum class Interpolation { kLinear, kNearest };

// Maps a raw image to the camera P: undistorts with K and distortion, rotates by R
// (x_rect = R x_raw). Pixels that fall outside the raw image read 0.
class RectifyMap {
 public:
  RectifyMap() = default;  // empty: Apply() returns its input
  RectifyMap(const cv::Matx33d& K, const cv::Mat& distortion, const cv::Matx33d& R, const cv::Matx33d& P,
             cv::Size size);

  [[nodiscard]] bool empty() const { return map_a_.empty(); }
  [[nodiscard]] cv::Mat Apply(const cv::Mat& raw, Interpolation interpolation = Interpolation::kLinear) const;

 private:
  cv::Mat map_a_, map_b_;  // cv::remap's fixed-point maps
};

// Camera matrix of the undistorted image of a single camera: alpha 0 keeps only valid pixels (no
// black border, larger focal length), 1 keeps every source pixel.
[[nodiscard]] cv::Matx33d UndistortedCameraMatrix(const cv::Matx33d& K, const cv::Mat& distortion, cv::Size size,
                                                  double alpha);

// Rectified stereo pair (cv::stereoRectify, zero disparity at infinity).
struct StereoRectification {
  cv::Matx33d R_left = cv::Matx33d::eye(), R_right = cv::Matx33d::eye();  // raw -> rectified frame
  cv::Matx34d P_left, P_right;  // rectified projections; P_right(0, 3) = -fx * baseline

  [[nodiscard]] double baseline_m() const { return -P_right(0, 3) / P_right(0, 0); }
};

// T_right_left maps left-camera coordinates into the right camera; both images have `size`.
[[nodiscard]] StereoRectification RectifyStereo(const cv::Matx33d& K_left, const cv::Mat& distortion_left,
                                                const cv::Matx33d& K_right, const cv::Mat& distortion_right,
                                                cv::Size size, const Eigen::Isometry3d& T_right_left, double alpha);

// The pose of a rectified camera in its raw camera's frame (the inverse of rotation R).
[[nodiscard]] Eigen::Isometry3d RawFromRectified(const cv::Matx33d& R);

}  // namespace flatslam
