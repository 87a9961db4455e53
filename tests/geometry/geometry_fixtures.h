// Shared pieces of the estimator tests: a test camera, pose construction, random directions,
// rotation errors.
#pragma once

#include <random>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "io/types.h"

namespace flatslam::testing {

inline constexpr double kPi = 3.14159265358979323846;
inline constexpr double kDeg = kPi / 180.0;

// 640x480 pinhole, fx = fy = 500, principal point at the centre.
inline PinholeCamera TestCamera() {
  PinholeCamera camera;
  camera.fx = 500;
  camera.fy = 500;
  camera.cx = 320;
  camera.cy = 240;
  camera.width = 640;
  camera.height = 480;
  return camera;
}

inline Eigen::Isometry3d Pose(const Eigen::Matrix3d& R, const Eigen::Vector3d& t) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = t;
  return T;
}

// A direction drawn uniformly from the unit sphere.
inline Eigen::Vector3d RandomUnit(std::mt19937_64& rng) {
  std::normal_distribution<double> n(0, 1);
  return Eigen::Vector3d(n(rng), n(rng), n(rng)).normalized();
}

// Angle of the rotation between two rotation matrices, in degrees.
inline double RotationErrorDeg(const Eigen::Matrix3d& R_est, const Eigen::Matrix3d& R_true) {
  return Eigen::AngleAxisd(R_est.transpose() * R_true).angle() / kDeg;
}

}  // namespace flatslam::testing
