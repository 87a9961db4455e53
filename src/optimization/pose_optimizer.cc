#include "optimization/pose_optimizer.h"

#include <array>
#include <cstdint>
#include <limits>

#include <ceres/ceres.h>

#include "core/error.h"
#include "core/requirements.h"
#include "optimization/lm_terms.h"

namespace flatslam {
namespace detail {
namespace {

Eigen::Vector3d LogSo3(const Eigen::Quaterniond& q) {
  const Eigen::AngleAxisd aa(q);
  return aa.angle() * aa.axis();
}

class PoseManifold final : public ceres::Manifold {
 public:
  int AmbientSize() const override { return kPoseParameterSize; }
  int TangentSize() const override { return 6; }

  bool Plus(const double* x, const double* delta, double* x_plus_delta) const override {
    const Eigen::Map<const Eigen::Quaterniond> q(x);
    const Eigen::Map<const Eigen::Vector3d> t(x + 4);
    const Eigen::Map<const Eigen::Vector3d> dw(delta);
    const Eigen::Map<const Eigen::Vector3d> dv(delta + 3);
    const Eigen::Quaterniond dq = ExpSo3Quaternion(dw);
    const Eigen::Quaterniond q_new = (dq * q).normalized();
    const Eigen::Vector3d t_new = dq * t + dv;
    Eigen::Map<Eigen::Quaterniond> q_out(x_plus_delta);
    Eigen::Map<Eigen::Vector3d> t_out(x_plus_delta + 4);
    q_out = q_new;
    t_out = t_new;
    return true;
  }
  bool PlusJacobian(const double* x, double* jacobian) const override {
    Eigen::Map<Eigen::Matrix<double, 7, 6, Eigen::RowMajor>> J(jacobian);
    J.setZero();
    J.topRows<6>().setIdentity();
    return true;
  }
  bool Minus(const double* y, const double* x, double* y_minus_x) const override {
    const Eigen::Map<const Eigen::Quaterniond> qx(x), qy(y);
    const Eigen::Map<const Eigen::Vector3d> tx(x + 4), ty(y + 4);
    const Eigen::Quaterniond dq = qy * qx.conjugate();
    Eigen::Map<Eigen::Vector3d> dw(y_minus_x);
    Eigen::Map<Eigen::Vector3d> dv(y_minus_x + 3);
    dw = LogSo3(dq);
    dv = ty - dq * tx;
    return true;
  }
  bool MinusJacobian(const double* x, double* jacobian) const override {
    Eigen::Map<Eigen::Matrix<double, 6, 7, Eigen::RowMajor>> J(jacobian);
    J.setZero();
    J.leftCols<6>().setIdentity();
    return true;
  }
};

}  // namespace

void PoseToParameters(const Eigen::Isometry3d& T_cam_world, double* parameters) {
  const Eigen::Quaterniond q(T_cam_world.linear());
  Eigen::Map<Eigen::Quaterniond> q_out(parameters);
  Eigen::Map<Eigen::Vector3d> t_out(parameters + 4);
  q_out = q.normalized();
  t_out = T_cam_world.translation();
}

Eigen::Isometry3d ParametersToPose(const double* parameters) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::Map<const Eigen::Quaterniond>(parameters).normalized().toRotationMatrix();
  T.translation() = Eigen::Map<const Eigen::Vector3d>(parameters + 4);
  return T;
}

std::unique_ptr<ceres::Manifold> MakePoseManifold() {
  return std::make_unique<PoseManifold>();
}

}  // namespace detail

namespace {

// Below this camera-frame depth a projection is treated as invalid.
constexpr double kMinDepth = 1e-6;

// Reprojection residual of a fixed world point against a pose block; stereo adds the right u.
// Inactive observations (outliers of the previous round) contribute nothing.
template <int kResiduals>
class PoseCost final : public ceres::SizedCostFunction<kResiduals, detail::kPoseParameterSize> {
 public:
  PoseCost(const PinholeCamera& camera, double bf, const PoseObservation& obs, const uint8_t* active)
      : fx_(camera.fx),
        fy_(camera.fy),
        cx_(camera.cx),
        cy_(camera.cy),
        bf_(bf),
        X_(obs.X_world),
        uv_(obs.uv),
        right_u_(obs.right_u),
        sqrt_info_(std::sqrt(static_cast<double>(obs.inv_sigma2))),
        active_(active) {}

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
    Eigen::Map<Eigen::Matrix<double, kResiduals, 1>> r(residuals);
    if (!*active_) {
      r.setZero();
      if (jacobians && jacobians[0])
        Eigen::Map<Eigen::Matrix<double, kResiduals, 7, Eigen::RowMajor>>(jacobians[0]).setZero();
      return true;
    }
    const Eigen::Map<const Eigen::Quaterniond> q(parameters[0]);
    const Eigen::Map<const Eigen::Vector3d> t(parameters[0] + 4);
    const Eigen::Vector3d xc = q * X_ + t;
    if (xc.z() <= kMinDepth) return false;  // the step crossed the image plane: reject it
    const double inv_z = 1.0 / xc.z();
    const double u = fx_ * xc.x() * inv_z + cx_;
    const double v = fy_ * xc.y() * inv_z + cy_;
    r(0) = sqrt_info_ * (uv_.x() - u);
    r(1) = sqrt_info_ * (uv_.y() - v);
    if constexpr (kResiduals == 3) r(2) = sqrt_info_ * (right_u_ - (u - bf_ * inv_z));
    if (jacobians && jacobians[0]) {
      // d(projection)/d(x_cam), then x_cam = Exp(delta) x_cam => d x_cam/d delta = [-[x_cam]x, I].
      Eigen::Matrix<double, kResiduals, 3> Jp;
      const double inv_z2 = inv_z * inv_z;
      Jp.row(0) << fx_ * inv_z, 0, -fx_ * xc.x() * inv_z2;
      Jp.row(1) << 0, fy_ * inv_z, -fy_ * xc.y() * inv_z2;
      if constexpr (kResiduals == 3) Jp.row(2) << fx_ * inv_z, 0, -fx_ * xc.x() * inv_z2 + bf_ * inv_z2;
      Eigen::Matrix3d skew;
      skew << 0, -xc.z(), xc.y(), xc.z(), 0, -xc.x(), -xc.y(), xc.x(), 0;
      Eigen::Map<Eigen::Matrix<double, kResiduals, 7, Eigen::RowMajor>> J(jacobians[0]);
      J.template leftCols<3>() = sqrt_info_ * Jp * skew;
      J.template middleCols<3>(3) = -sqrt_info_ * Jp;
      J.col(6).setZero();
    }
    return true;
  }

 private:
  double fx_, fy_, cx_, cy_, bf_;
  Eigen::Vector3d X_;
  Eigen::Vector2d uv_;
  double right_u_;
  double sqrt_info_;
  const uint8_t* active_;
};

// Unwhitened chi2 (residual^2 * inv_sigma2) of an observation; infinity behind the camera.
double Chi2(const PinholeCamera& camera, double bf, const Eigen::Isometry3d& T, const PoseObservation& obs) {
  const Eigen::Vector3d xc = T * obs.X_world;
  if (xc.z() <= kMinDepth) return std::numeric_limits<double>::infinity();
  const double inv_z = 1.0 / xc.z();
  const double u = camera.fx * xc.x() * inv_z + camera.cx;
  const double v = camera.fy * xc.y() * inv_z + camera.cy;
  double e2 = (obs.uv - Eigen::Vector2d(u, v)).squaredNorm();
  if (obs.right_u >= 0) {
    const double er = obs.right_u - (u - bf * inv_z);
    e2 += er * er;
  }
  return e2 * obs.inv_sigma2;
}

}  // namespace

PoseOptimizationResult OptimizePose(const PinholeCamera& camera, double baseline_m,
                                    const Eigen::Isometry3d& T_cam_world_initial,
                                    const std::vector<PoseObservation>& observations,
                                    const PoseOptimizerOptions& options) {
  FLATSLAM_CHECK(options.Check(), "OptimizePose: invalid PoseOptimizerOptions");
  FLATSLAM_CHECK(camera.fx > 0 && camera.fy > 0, "OptimizePose: camera has no focal length");
  const size_t n = observations.size();
  const double bf = camera.fx * baseline_m;
  for (size_t i = 0; i < n; ++i) {
    FLATSLAM_CHECK(observations[i].inv_sigma2 > 0, "OptimizePose: observation ", i, " has inv_sigma2 <= 0");
    FLATSLAM_CHECK(observations[i].right_u < 0 || baseline_m > 0, "OptimizePose: stereo observation ", i,
                   " but baseline_m = ", baseline_m);
  }

  PoseOptimizationResult result;
  result.T_cam_world = T_cam_world_initial;
  result.inlier.assign(n, false);

  std::vector<uint8_t> active(n, 1);
  std::array<double, detail::kPoseParameterSize> pose;
  detail::PoseToParameters(T_cam_world_initial, pose.data());

  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  problem_options.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  problem_options.enable_fast_removal = false;
  problem_options.disable_all_safety_checks = true;
  ceres::Problem problem(problem_options);
  const std::unique_ptr<ceres::Manifold> manifold = detail::MakePoseManifold();
  problem.AddParameterBlock(pose.data(), detail::kPoseParameterSize, manifold.get());
  ceres::LossFunctionWrapper loss_mono(new ceres::HuberLoss(options.huber_mono), ceres::TAKE_OWNERSHIP);
  ceres::LossFunctionWrapper loss_stereo(new ceres::HuberLoss(options.huber_stereo), ceres::TAKE_OWNERSHIP);
  for (size_t i = 0; i < n; ++i) {
    const PoseObservation& obs = observations[i];
    if (obs.right_u >= 0)
      problem.AddResidualBlock(new PoseCost<3>(camera, bf, obs, &active[i]), &loss_stereo, pose.data());
    else
      problem.AddResidualBlock(new PoseCost<2>(camera, bf, obs, &active[i]), &loss_mono, pose.data());
  }

  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::DENSE_NORMAL_CHOLESKY;
  solver_options.max_num_iterations = options.iterations_per_round;
  solver_options.num_threads = 1;
  solver_options.logging_type = ceres::SILENT;
  solver_options.minimizer_progress_to_stdout = false;

  // Observations behind the initial pose cannot be evaluated: start them as outliers.
  Eigen::Isometry3d T = T_cam_world_initial;
  int num_active = 0;
  for (size_t i = 0; i < n; ++i) {
    active[i] = (T * observations[i].X_world).z() > kMinDepth;
    num_active += active[i];
  }

  for (int round = 0; round < options.rounds; ++round) {
    if (num_active < options.min_observations || num_active == 0) return result;  // success = false
    if (round == options.rounds - 1 && !options.robust_last_round) {
      loss_mono.Reset(nullptr, ceres::TAKE_OWNERSHIP);
      loss_stereo.Reset(nullptr, ceres::TAKE_OWNERSHIP);
    }
    ceres::Solver::Summary summary;
    ceres::Solve(solver_options, &problem, &summary);
    if (summary.termination_type == ceres::FAILURE || !summary.IsSolutionUsable()) return result;
    T = detail::ParametersToPose(pose.data());
    // Every observation is re-classified, so a point rejected early can come back.
    num_active = 0;
    for (size_t i = 0; i < n; ++i) {
      const double gate = observations[i].right_u >= 0 ? options.chi2_stereo : options.chi2_mono;
      active[i] = Chi2(camera, bf, T, observations[i]) <= gate;
      num_active += active[i];
    }
  }

  result.T_cam_world = T;
  for (size_t i = 0; i < n; ++i) result.inlier[i] = active[i] != 0;
  result.num_inliers = num_active;
  result.success = num_active >= options.min_observations;
  return result;
}

}  // namespace flatslam
