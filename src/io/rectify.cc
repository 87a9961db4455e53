#include "io/rectify.h"

#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>

namespace flatslam {

RectifyMap::RectifyMap(const cv::Matx33d& K, const cv::Mat& distortion, const cv::Matx33d& R, const cv::Matx33d& P,
                       cv::Size size) {
  cv::initUndistortRectifyMap(cv::Mat(K), distortion, cv::Mat(R), cv::Mat(P), size, CV_16SC2, map_a_, map_b_);
}

cv::Mat RectifyMap::Apply(const cv::Mat& raw, Interpolation interpolation) const {
  if (empty()) return raw;
  cv::Mat out;
  cv::remap(raw, out, map_a_, map_b_, interpolation == Interpolation::kNearest ? cv::INTER_NEAREST : cv::INTER_LINEAR,
            cv::BORDER_CONSTANT, cv::Scalar(0));
  return out;
}

cv::Matx33d UndistortedCameraMatrix(const cv::Matx33d& K, const cv::Mat& distortion, cv::Size size, double alpha) {
  return cv::Matx33d(cv::getOptimalNewCameraMatrix(cv::Mat(K), distortion, size, alpha, size));
}

StereoRectification RectifyStereo(const cv::Matx33d& K_left, const cv::Mat& distortion_left, const cv::Matx33d& K_right,
                                  const cv::Mat& distortion_right, cv::Size size, const Eigen::Isometry3d& T_right_left,
                                  double alpha) {
  cv::Matx33d R;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) R(r, c) = T_right_left.linear()(r, c);
  const cv::Vec3d T(T_right_left.translation().x(), T_right_left.translation().y(), T_right_left.translation().z());
  cv::Mat R0, R1, P0, P1, Q;
  cv::stereoRectify(cv::Mat(K_left), distortion_left, cv::Mat(K_right), distortion_right, size, cv::Mat(R), cv::Mat(T),
                    R0, R1, P0, P1, Q, cv::CALIB_ZERO_DISPARITY, alpha, size);
  StereoRectification out;
  out.R_left = cv::Matx33d(R0);
  out.R_right = cv::Matx33d(R1);
  out.P_left = cv::Matx34d(P0);
  out.P_right = cv::Matx34d(P1);
  return out;
}

Eigen::Isometry3d RawFromRectified(const cv::Matx33d& R) {
  Eigen::Matrix3d R_rect_raw;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) R_rect_raw(r, c) = R(r, c);
  Eigen::Isometry3d T_raw_rect = Eigen::Isometry3d::Identity();
  T_raw_rect.linear() = R_rect_raw.transpose();
  return T_raw_rect;
}

}  // namespace flatslam
