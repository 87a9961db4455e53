// Small pieces shared by the hand-written Levenberg-Marquardt solvers (bundle_adjustment_lm.cc,
// mapping/camera_check.cc) and the pose optimizer's manifold: the rotation of a left perturbation
// (as a matrix or a quaternion) and Huber's robust cost.
// Concurrency: pure functions.
#pragma once

#include <cmath>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace flatslam::detail {

// [v]x: the cross product with v as a matrix.
inline Eigen::Matrix3d Skew(const Eigen::Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

// The rotation exp([w]x); to first order below 1e-12 rad.
inline Eigen::Matrix3d ExpSo3(const Eigen::Vector3d& w) {
  const double theta = w.norm();
  if (theta < 1e-12) return Eigen::Matrix3d::Identity() + Skew(w);
  return Eigen::AngleAxisd(theta, w / theta).toRotationMatrix();
}

// The same rotation as a unit quaternion, for parameters stored as quaternions (the pose
// optimizer's manifold); to first order below 1e-12 rad.
inline Eigen::Quaterniond ExpSo3Quaternion(const Eigen::Vector3d& w) {
  const double theta = w.norm();
  if (theta < 1e-12) return Eigen::Quaterniond(1.0, 0.5 * w.x(), 0.5 * w.y(), 0.5 * w.z()).normalized();
  return Eigen::Quaterniond(Eigen::AngleAxisd(theta, w / theta));
}

// Huber on the squared whitened error s: rho(s) (the cost is half of it, as in Ceres) and its
// derivative rho'(s), the residual's weight in the normal equations. Not robust: rho = s.
inline void Huber(double s, double delta, bool robust, double* rho, double* weight) {
  if (!robust || s <= delta * delta) {
    *rho = s;
    *weight = 1.0;
    return;
  }
  const double e = std::sqrt(s);
  *rho = 2.0 * delta * e - delta * delta;
  *weight = delta / e;
}

}  // namespace flatslam::detail
