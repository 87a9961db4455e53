// Points of a bundle adjustment in inverse depth, and their reprojection: the one kernel both
// solvers (flatslam's Schur LM and the Ceres path) evaluate.
//
// A point is theta = (alpha, beta, rho) in the camera of an anchor pose held constant for the
// pass: X = R_a' ((alpha, beta, 1) / rho - t_a). Its homogeneous world point is
// q = rho X = map theta + offset, and in camera k, h = R_k q + rho t_k = rho x_cam. In world
// coordinates a far point seen along nearly parallel rays has almost no curvature along its ray,
// so a damped step bounds that direction hardly at all: on a motorway, steps moved such points by
// kilometres and, half the time, behind a camera, and the step was rejected. In inverse depth
// that direction is rho, on which the cost is nearly quadratic out to rho = 0 (infinity), and
// projections stay defined through it. The anchor is a constant, so each observation still
// couples one pose with one point. A point without an anchor is a world point (theta = X,
// rho = 1, h = x_cam): the same kernel evaluates both (BundleAdjustmentOptions::
// inverse_depth_points chooses; docs/STATUS.md has what each gives on the benchmarks).
// Concurrency: pure functions.
#pragma once

#include <Eigen/Core>

#include "io/types.h"

namespace flatslam::detail {

// Below this |h_z| a projection is treated as invalid (behind or on the image plane).
inline constexpr double kMinHomogeneousDepth = 1e-6;

struct InverseDepthAnchor {
  Eigen::Matrix3d map;     // d q / d theta: (R_a' e_x, R_a' e_y, -R_a' t_a)
  Eigen::Vector3d offset;  // R_a' e_z

  // The anchor of a camera pose (camera from world: x = R X + t).
  static InverseDepthAnchor Of(const Eigen::Matrix3d& R, const Eigen::Vector3d& t) {
    InverseDepthAnchor a;
    const Eigen::Matrix3d Rt = R.transpose();
    a.map << Rt.col(0), Rt.col(1), -Rt * t;
    a.offset = Rt.col(2);
    return a;
  }
  [[nodiscard]] Eigen::Vector3d Homogeneous(const Eigen::Vector3d& theta) const { return map * theta + offset; }
};

// Whether BundleAdjustmentOptions::inverse_depth_points (0 none, 1 points without a stereo or
// depth observation, 2 all) puts a point in inverse depth.
inline bool InInverseDepth(int inverse_depth_points, bool measured_depth) {
  return inverse_depth_points == 2 || (inverse_depth_points == 1 && !measured_depth);
}

// theta of world point X in the anchor's camera (R, t); X must be in front of it.
inline Eigen::Vector3d ToInverseDepth(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const Eigen::Vector3d& X) {
  const Eigen::Vector3d x = R * X + t;
  return {x.x() / x.z(), x.y() / x.z(), 1.0 / x.z()};
}

// The world point of theta. False, leaving *X as it was, where rho <= 0: the adjustment moved the
// point to or beyond infinity, where it has no position in front of the cameras.
inline bool FromInverseDepth(const InverseDepthAnchor& anchor, const Eigen::Vector3d& theta, Eigen::Vector3d* X) {
  if (!(theta.z() > 0)) return false;
  *X = anchor.Homogeneous(theta) / theta.z();
  return true;
}

// Reprojection of the homogeneous point (q, rho) in the camera (R, t): h = R q + rho t, the
// residual measured - predicted (left u, v; N = 3 adds the right image's u, whose disparity is
// bf / z = bf rho / h_z), and, when J is given, d predicted / d h. False where h is behind the
// camera or on its image plane.
template <int N>
bool ReprojectHomogeneous(const PinholeCamera& c, double bf, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                          const Eigen::Vector3d& q, double rho, const Eigen::Vector2d& uv, double right_u,
                          Eigen::Vector3d* h, Eigen::Matrix<double, N, 1>* r, Eigen::Matrix<double, N, 3>* J) {
  *h = R * q + rho * t;
  if (h->z() <= kMinHomogeneousDepth) return false;
  const double inv_z = 1.0 / h->z();
  const double u = c.fx * h->x() * inv_z + c.cx;
  const double v = c.fy * h->y() * inv_z + c.cy;
  (*r)(0) = uv.x() - u;
  (*r)(1) = uv.y() - v;
  if constexpr (N == 3) (*r)(2) = right_u - (u - bf * rho * inv_z);
  if (J) {
    const double inv_z2 = inv_z * inv_z;
    J->row(0) << c.fx * inv_z, 0, -c.fx * h->x() * inv_z2;
    J->row(1) << 0, c.fy * inv_z, -c.fy * h->y() * inv_z2;
    if constexpr (N == 3) J->row(2) << c.fx * inv_z, 0, -c.fx * h->x() * inv_z2 + bf * rho * inv_z2;
  }
  return true;
}

// From d predicted / d h (J, at h, rho) to the derivatives w.r.t. the pose's left perturbation
// [w, v] (d h = [-[h]x, rho I]) and w.r.t. the point's parameters: theta of an inverse-depth
// point (d h / d theta = R map + t e_rho'; the disparity also reads rho itself), or, without an
// anchor, a world point (rho = 1, h = x_cam, d h / d X = R).
template <int N>
void PointJacobians(const Eigen::Matrix<double, N, 3>& J, const Eigen::Vector3d& h, double rho, double bf,
                    const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const InverseDepthAnchor* anchor,
                    Eigen::Matrix<double, N, 6>* J_pose, Eigen::Matrix<double, N, 3>* J_point) {
  if (J_point && anchor) {
    *J_point = (J * R) * anchor->map;
    J_point->col(2) += J * t;
    if constexpr (N == 3) (*J_point)(2, 2) -= bf / h.z();
  } else if (J_point) {
    *J_point = J * R;
  }
  if (J_pose) {
    J_pose->template rightCols<3>() = rho * J;
    J_pose->col(0) = J.col(1) * -h.z() + J.col(2) * h.y();
    J_pose->col(1) = J.col(0) * h.z() - J.col(2) * h.x();
    J_pose->col(2) = J.col(1) * h.x() - J.col(0) * h.y();
  }
}

}  // namespace flatslam::detail
