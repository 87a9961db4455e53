#include "optimization/bundle_adjustment.h"

#include <array>
#include <limits>
#include <memory>
#include <optional>

#include <ceres/ceres.h>

#include "core/error.h"
#include "core/requirements.h"
#include "optimization/bundle_adjustment_lm.h"
#include "optimization/inverse_depth.h"
#include "optimization/pose_optimizer.h"

namespace flatslam {
namespace {

// Below this camera-frame depth a projection is treated as invalid.
constexpr double kMinDepth = 1e-6;

using PoseBlock = std::array<double, detail::kPoseParameterSize>;

// Reprojection residual of a point block (in inverse depth with an anchor, see
// optimization/inverse_depth.h, else in world coordinates) in a pose block; stereo adds the
// right-image u.
template <int kResiduals>
class BaCost final : public ceres::SizedCostFunction<kResiduals, detail::kPoseParameterSize, 3> {
 public:
  BaCost(const PinholeCamera& camera, double bf, const BundleAdjustmentObservation& obs,
         const std::optional<detail::InverseDepthAnchor>& anchor)
      : camera_(camera),
        bf_(bf),
        uv_(obs.uv),
        right_u_(obs.right_u),
        sqrt_info_(std::sqrt(static_cast<double>(obs.inv_sigma2))),
        anchor_(anchor) {}

  bool Evaluate(double const* const* parameters, double* residuals, double** jacobians) const override {
    const Eigen::Matrix3d R = Eigen::Map<const Eigen::Quaterniond>(parameters[0]).toRotationMatrix();
    const Eigen::Map<const Eigen::Vector3d> t(parameters[0] + 4);
    const Eigen::Map<const Eigen::Vector3d> theta(parameters[1]);
    const bool want_jacobians = jacobians && (jacobians[0] || jacobians[1]);
    Eigen::Vector3d h;
    Eigen::Matrix<double, kResiduals, 1> r;
    Eigen::Matrix<double, kResiduals, 3> J;
    // Behind the camera: the step crossed the image plane, reject it.
    const double rho = anchor_ ? theta.z() : 1.0;
    const Eigen::Vector3d q = anchor_ ? anchor_->Homogeneous(theta) : Eigen::Vector3d(theta);
    if (!detail::ReprojectHomogeneous<kResiduals>(camera_, bf_, R, t, q, rho, uv_, right_u_, &h, &r,
                                                  want_jacobians ? &J : nullptr))
      return false;
    Eigen::Map<Eigen::Matrix<double, kResiduals, 1>> residual(residuals);
    residual = sqrt_info_ * r;
    if (!want_jacobians) return true;
    Eigen::Matrix<double, kResiduals, 6> J_pose;
    Eigen::Matrix<double, kResiduals, 3> J_point;
    detail::PointJacobians<kResiduals>(J, h, rho, bf_, R, t, anchor_ ? &*anchor_ : nullptr, &J_pose, &J_point);
    // Residuals are measured - predicted, whitened.
    if (jacobians[0]) {
      Eigen::Map<Eigen::Matrix<double, kResiduals, 7, Eigen::RowMajor>> Jm(jacobians[0]);
      Jm.template leftCols<6>() = -sqrt_info_ * J_pose;
      Jm.col(6).setZero();
    }
    if (jacobians[1]) {
      Eigen::Map<Eigen::Matrix<double, kResiduals, 3, Eigen::RowMajor>> Jm(jacobians[1]);
      Jm = -sqrt_info_ * J_point;
    }
    return true;
  }

 private:
  PinholeCamera camera_;
  double bf_;
  Eigen::Vector2d uv_;
  double right_u_;
  double sqrt_info_;
  std::optional<detail::InverseDepthAnchor> anchor_;  // none: a world point
};

// Left-image pixel error and unwhitened chi2 of one observation; nullopt behind the camera.
struct ObservationError {
  double pixel2 = 0;  // squared left-image error
  double chi2 = 0;    // (left + right) squared error * inv_sigma2
};

std::optional<ObservationError> EvaluateObservation(const PinholeCamera& camera, double bf,
                                                    const Eigen::Isometry3d& T_cam_world, const Eigen::Vector3d& X,
                                                    const BundleAdjustmentObservation& obs) {
  const Eigen::Vector3d xc = T_cam_world * X;
  if (xc.z() <= kMinDepth) return std::nullopt;
  const double inv_z = 1.0 / xc.z();
  const double u = camera.fx * xc.x() * inv_z + camera.cx;
  const double v = camera.fy * xc.y() * inv_z + camera.cy;
  ObservationError e;
  e.pixel2 = (obs.uv - Eigen::Vector2d(u, v)).squaredNorm();
  double e2 = e.pixel2;
  if (obs.right_u >= 0) {
    const double er = obs.right_u - (u - bf * inv_z);
    e2 += er * er;
  }
  e.chi2 = e2 * obs.inv_sigma2;
  return e;
}

// Runs one Ceres pass over the active observations; returns the summary's usability.
bool SolvePassCeres(const BundleAdjustmentProblem& input, const BundleAdjustmentOptions& options,
                    const std::vector<uint8_t>& active, bool robust, int iterations, bool dense,
                    std::vector<Eigen::Isometry3d>* isometries, std::vector<Eigen::Vector3d>* points,
                    int* iterations_done, bool* stopped, detail::SchurWorkspace* /*unused*/) {
  std::vector<PoseBlock> blocks(isometries->size());
  for (size_t k = 0; k < blocks.size(); ++k) detail::PoseToParameters((*isometries)[k], blocks[k].data());
  std::vector<PoseBlock>* poses = &blocks;
  const double bf = input.camera.fx * input.baseline_m;
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  problem_options.manifold_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  problem_options.disable_all_safety_checks = true;
  ceres::Problem problem(problem_options);
  const std::unique_ptr<ceres::Manifold> manifold = detail::MakePoseManifold();
  ceres::HuberLoss loss_mono(options.huber_mono);
  ceres::HuberLoss loss_stereo(options.huber_stereo);

  const size_t num_poses = poses->size();
  std::vector<uint8_t> pose_added(num_poses, 0), point_added(points->size(), 0);
  // Points in inverse depth where options.inverse_depth_points asks, anchored as flatslam's
  // solver anchors them: in the first camera, in observation order, that sees the point in front.
  std::vector<uint8_t> measured_depth(points->size(), 0);
  if (options.inverse_depth_points == 1)
    for (size_t i = 0; i < input.observations.size(); ++i)
      if (active[i] && input.observations[i].right_u >= 0) measured_depth[input.observations[i].point_index] = 1;
  std::vector<Eigen::Vector3d> theta = *points;
  std::vector<std::optional<detail::InverseDepthAnchor>> anchors(points->size());
  std::vector<uint8_t> anchored(points->size(), 0);
  for (size_t i = 0; i < input.observations.size(); ++i) {
    const BundleAdjustmentObservation& obs = input.observations[i];
    if (!active[i] || anchored[obs.point_index]) continue;
    if (!detail::InInverseDepth(options.inverse_depth_points, measured_depth[obs.point_index])) continue;
    const Eigen::Isometry3d& T = (*isometries)[obs.pose_index];
    const Eigen::Vector3d& X = (*points)[obs.point_index];
    if ((T * X).z() <= detail::kMinHomogeneousDepth) continue;
    anchors[obs.point_index] = detail::InverseDepthAnchor::Of(T.linear(), T.translation());
    theta[obs.point_index] = detail::ToInverseDepth(T.linear(), T.translation(), X);
    anchored[obs.point_index] = 1;
  }
  auto ordering = std::make_shared<ceres::ParameterBlockOrdering>();
  int residuals = 0;
  for (size_t i = 0; i < input.observations.size(); ++i) {
    if (!active[i]) continue;
    const BundleAdjustmentObservation& obs = input.observations[i];
    double* pose = (*poses)[obs.pose_index].data();
    double* point = theta[obs.point_index].data();
    if (!pose_added[obs.pose_index]) {
      pose_added[obs.pose_index] = 1;
      problem.AddParameterBlock(pose, detail::kPoseParameterSize, manifold.get());
      if (input.poses[obs.pose_index].fixed) problem.SetParameterBlockConstant(pose);
      ordering->AddElementToGroup(pose, 1);
    }
    if (!point_added[obs.point_index]) {
      point_added[obs.point_index] = 1;
      problem.AddParameterBlock(point, 3);
      ordering->AddElementToGroup(point, 0);  // points are eliminated first (Schur complement)
    }
    const std::optional<detail::InverseDepthAnchor>& anchor = anchors[obs.point_index];
    if (obs.right_u >= 0)
      problem.AddResidualBlock(new BaCost<3>(input.camera, bf, obs, anchor), robust ? &loss_stereo : nullptr, pose,
                               point);
    else
      problem.AddResidualBlock(new BaCost<2>(input.camera, bf, obs, anchor), robust ? &loss_mono : nullptr, pose,
                               point);
    ++residuals;
  }
  if (residuals == 0) return true;

  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = dense ? ceres::DENSE_SCHUR : ceres::SPARSE_SCHUR;
  if (options.linear_solver == BundleAdjustmentOptions::LinearSolver::kIterativeSchur) {
    solver_options.linear_solver_type = ceres::ITERATIVE_SCHUR;
    solver_options.preconditioner_type = ceres::SCHUR_JACOBI;
    solver_options.eta = detail::kIterativeSchurTolerance;
  }
  solver_options.linear_solver_ordering = ordering;
  solver_options.max_num_iterations = iterations;
  solver_options.num_threads = options.num_threads;
  solver_options.logging_type = ceres::SILENT;
  solver_options.minimizer_progress_to_stdout = false;
  struct StopEarly final : ceres::IterationCallback {
    const std::function<bool()>* stop;
    explicit StopEarly(const std::function<bool()>* s) : stop(s) {}
    ceres::CallbackReturnType operator()(const ceres::IterationSummary&) override {
      return (*stop)() ? ceres::SOLVER_TERMINATE_SUCCESSFULLY : ceres::SOLVER_CONTINUE;
    }
  } stop_early(&options.stop_early);
  if (options.stop_early) solver_options.callbacks.push_back(&stop_early);
  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);
  if (options.stop_early && options.stop_early()) *stopped = true;
  *iterations_done += static_cast<int>(summary.iterations.size());
  // Ceres leaves the parameters at the last accepted iterate even when it reports failure.
  for (size_t k = 0; k < blocks.size(); ++k)
    if (!input.poses[k].fixed) (*isometries)[k] = detail::ParametersToPose(blocks[k].data());
  for (size_t j = 0; j < points->size(); ++j)
    if (!anchored[j])
      (*points)[j] = theta[j];
    else
      detail::FromInverseDepth(*anchors[j], theta[j], &(*points)[j]);
  return summary.IsSolutionUsable();
}

}  // namespace

BundleAdjustmentWorkspace::BundleAdjustmentWorkspace() : schur_(detail::MakeSchurWorkspace()) {}

BundleAdjustmentResult LocalBundleAdjustment(BundleAdjustmentProblem& problem, const BundleAdjustmentOptions& options,
                                             BundleAdjustmentWorkspace* workspace) {
  FLATSLAM_CHECK(options.Check(), "LocalBundleAdjustment: invalid BundleAdjustmentOptions");
  FLATSLAM_CHECK(problem.camera.fx > 0 && problem.camera.fy > 0, "LocalBundleAdjustment: camera has no focal length");
  const size_t num_obs = problem.observations.size();
  for (size_t i = 0; i < num_obs; ++i) {
    const BundleAdjustmentObservation& obs = problem.observations[i];
    FLATSLAM_CHECK(obs.pose_index < problem.poses.size(), "LocalBundleAdjustment: observation ", i, " has pose_index ",
                   obs.pose_index, " of ", problem.poses.size());
    FLATSLAM_CHECK(obs.point_index < problem.points.size(), "LocalBundleAdjustment: observation ", i,
                   " has point_index ", obs.point_index, " of ", problem.points.size());
    FLATSLAM_CHECK(obs.inv_sigma2 > 0, "LocalBundleAdjustment: observation ", i, " has inv_sigma2 <= 0");
    FLATSLAM_CHECK(obs.right_u < 0 || problem.baseline_m > 0, "LocalBundleAdjustment: stereo observation ", i,
                   " but baseline_m = ", problem.baseline_m);
  }

  std::vector<Eigen::Isometry3d> poses(problem.poses.size());
  size_t free_poses = 0;
  for (size_t k = 0; k < poses.size(); ++k) {
    poses[k] = problem.poses[k].T_cam_world;
    free_poses += !problem.poses[k].fixed;
  }
  std::vector<Eigen::Vector3d> points = problem.points;
  const bool dense = options.linear_solver == BundleAdjustmentOptions::LinearSolver::kDenseSchur ||
                     (options.linear_solver == BundleAdjustmentOptions::LinearSolver::kAuto &&
                      free_poses <= static_cast<size_t>(options.dense_schur_max_poses));
  const bool ceres = options.solver == BundleAdjustmentOptions::Solver::kCeres ||
                     (free_poses > static_cast<size_t>(options.schur_lm_max_poses) &&
                      options.linear_solver != BundleAdjustmentOptions::LinearSolver::kIterativeSchur);
  const auto solve_pass = ceres ? SolvePassCeres : detail::SolvePassSchurLm;
  const double bf = problem.camera.fx * problem.baseline_m;

  BundleAdjustmentResult result;
  result.outlier.assign(num_obs, false);

  // Observations behind their camera at the start cannot be evaluated: they begin as outliers.
  std::vector<uint8_t> active(num_obs, 0);
  double sum2 = 0;
  size_t counted = 0;
  for (size_t i = 0; i < num_obs; ++i) {
    const BundleAdjustmentObservation& obs = problem.observations[i];
    const auto e = EvaluateObservation(problem.camera, bf, poses[obs.pose_index], points[obs.point_index], obs);
    if (!e) continue;
    active[i] = 1;
    sum2 += e->pixel2;
    ++counted;
  }
  result.initial_rmse_px = counted ? std::sqrt(sum2 / (2.0 * counted)) : 0;

  // Classifies every observation against the chi2 gate at the current estimate.
  auto classify = [&]() {
    for (size_t i = 0; i < num_obs; ++i) {
      const BundleAdjustmentObservation& obs = problem.observations[i];
      const auto e = EvaluateObservation(problem.camera, bf, poses[obs.pose_index], points[obs.point_index], obs);
      const double gate = obs.right_u >= 0 ? options.chi2_stereo : options.chi2_mono;
      active[i] = e && e->chi2 <= gate;
    }
  };

  detail::SchurWorkspace* schur = workspace ? workspace->schur() : nullptr;
  bool usable = solve_pass(problem, options, active, /*robust=*/true, options.first_pass_iterations, dense, &poses,
                           &points, &result.iterations, &result.stopped_early, schur);
  if (usable && options.second_pass_iterations > 0 && !result.stopped_early) {
    classify();
    usable = solve_pass(problem, options, active, options.robust_second_pass, options.second_pass_iterations, dense,
                        &poses, &points, &result.iterations, &result.stopped_early, schur);
  }
  classify();

  for (size_t k = 0; k < poses.size(); ++k)
    if (!problem.poses[k].fixed) problem.poses[k].T_cam_world = poses[k];
  problem.points = points;

  double sum_norm = 0;
  sum2 = 0;
  counted = 0;
  for (size_t i = 0; i < num_obs; ++i) {
    result.outlier[i] = !active[i];
    if (!active[i]) {
      ++result.num_outliers;
      continue;
    }
    const BundleAdjustmentObservation& obs = problem.observations[i];
    const auto e = EvaluateObservation(problem.camera, bf, poses[obs.pose_index], points[obs.point_index], obs);
    sum2 += e->pixel2;
    sum_norm += std::sqrt(e->pixel2);
    ++counted;
  }
  result.final_rmse_px = counted ? std::sqrt(sum2 / (2.0 * counted)) : 0;
  result.final_mean_error_px = counted ? sum_norm / counted : 0;
  result.success = usable;
  return result;
}

}  // namespace flatslam
