// Local bundle adjustment over keyframe poses and map points given as plain arrays: a robust
// pass, chi-square outlier removal, then a refining pass, each a Levenberg-Marquardt solve with
// the points eliminated (Schur complement). Two solvers: flatslam's own (the default: structure
// built once per pass, no per-iteration allocation) and Ceres (the reference it is tested against).
// Concurrency: stateless; one call owns its problem. flatslam's solver runs its passes over the
// points on schur_lm_threads TBB workers, with the same bits on any number; Ceres threads only if
// num_threads > 1 (and its result may then vary from run to run).
#pragma once

#include <cmath>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/option_fields.h"
#include "optimization/outlier_gates.h"
#include "io/types.h"

namespace flatslam {

struct BundleAdjustmentPose {
  Eigen::Isometry3d T_cam_world = Eigen::Isometry3d::Identity();
  bool fixed = false;  // held constant (e.g. keyframes outside the local window)
};

struct BundleAdjustmentObservation {
  uint32_t pose_index = 0;                       // into BundleAdjustmentProblem::poses
  uint32_t point_index = 0;                      // into BundleAdjustmentProblem::points
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();  // left-image pixel, undistorted
  double right_u = -1;                           // rectified right-image x; < 0 = mono observation
  float inv_sigma2 = 1.0f;                       // 1 / scale_factor^(2 octave)
};

// Input and output: poses and points are overwritten with the optimized values.
struct BundleAdjustmentProblem {
  PinholeCamera camera;
  double baseline_m = 0;  // needed only for stereo observations
  std::vector<BundleAdjustmentPose> poses;
  std::vector<Eigen::Vector3d> points;  // X_world
  std::vector<BundleAdjustmentObservation> observations;
};

struct BundleAdjustmentOptions {
  // kIterativeSchur: conjugate gradients on the reduced camera system, preconditioned by its
  // 6x6 diagonal blocks; the system stays implicit (each product passes over the observations),
  // so memory follows the observations, never the pairs of keyframes that share points nor a
  // factor's fill, and whole merged maps of a thousand keyframes and more stay in flatslam's own
  // solver (schur_lm_max_poses does not apply to it).
  enum class LinearSolver { kAuto, kDenseSchur, kSparseSchur, kIterativeSchur };
  enum class Solver { kSchurLm, kCeres };

// X(type, name, default, requirement, description) (core/option_fields.h).
#define FLATSLAM_BUNDLE_ADJUSTMENT_OPTIONS(X)                                                                         \
  X(Solver, solver, Solver::kSchurLm, true, "schur_lm, or ceres: the same passes through Ceres (reference path)")     \
  X(int, first_pass_iterations, 5, first_pass_iterations >= 1,                                                        \
    "robust pass before outlier classification (ORB-SLAM2: 5)")                                                       \
  X(int, second_pass_iterations, 10, second_pass_iterations >= 0, "pass on inliers only (ORB-SLAM2: 10); 0 skips it") \
  FLATSLAM_OUTLIER_GATE_OPTIONS(X)                                                                                    \
  X(bool, robust_second_pass, false, true, "keep the robust kernel in the second pass (ORB-SLAM2 drops it)")          \
  X(int, inverse_depth_points, 0, inverse_depth_points >= 0 && inverse_depth_points <= 2,                             \
    "points adjusted in inverse depth (optimization/inverse_depth.h): 0 none (world coordinates), 1 those without a "  \
    "stereo or depth observation, 2 all")                                                                             \
  X(int, dense_schur_max_poses, 40, dense_schur_max_poses >= 0,                                                       \
    "automatic linear solver: dense Schur up to this many free poses, else sparse")                                   \
  X(int, schur_lm_max_poses, 150, schur_lm_max_poses >= 0,                                                            \
    "schur_lm hands problems with more free poses than this to Ceres, whose sparse Schur runs on CHOLMOD's "          \
    "supernodal factorization (Eigen's simplicial LDLT took 60% of a 1,125-keyframe merge weld); local BA "           \
    "windows stay well below it")                                                                                     \
  X(int, num_threads, 1, num_threads >= 1, "Ceres threads; 1 keeps the call single-threaded")                       \
  X(int, schur_lm_threads, 0, schur_lm_threads >= 0,                                                                  \
    "threads of flatslam's own solver (schur_lm), which gives the same bits on any number: 0 = those of the calling " \
    "task arena (every core, unless the caller limits it), 1 = the calling thread only")

  FLATSLAM_BUNDLE_ADJUSTMENT_OPTIONS(FLATSLAM_OPTION_FIELD)
  // Not settable by name.
  LinearSolver linear_solver = LinearSolver::kAuto;
  // Asked after every solver iteration; true ends the solve at the current iterate (the
  // outlier classification still runs). Local mapping uses it to yield to a waiting keyframe.
  std::function<bool()> stop_early;

  FLATSLAM_OPTION_MEMBERS(FLATSLAM_BUNDLE_ADJUSTMENT_OPTIONS)
  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const {
    return FieldsProblem();
  }
  [[nodiscard]] bool Check() const {
    return Problem().empty();
  }
};

struct BundleAdjustmentResult {
  bool success = false;       // false: the solver failed (problem left at its last usable state)
  std::vector<bool> outlier;  // per observation: failed the chi2 / depth test after the last pass
  int num_outliers = 0;
  double initial_rmse_px = 0;      // per-coordinate RMSE of left-image errors, all observations in front
  double final_rmse_px = 0;        // per-coordinate RMSE of left-image errors, inliers
  double final_mean_error_px = 0;  // mean left-image reprojection error (norm), inliers
  int iterations = 0;              // solver iterations over both passes
  bool stopped_early = false;      // options.stop_early ended it
};

namespace detail {
struct SchurWorkspace;
struct SchurWorkspaceDeleter {
  void operator()(SchurWorkspace* w) const;
};
}  // namespace detail

// Buffers that a caller adjusting often (local mapping) keeps between calls, so that a long
// session does not reallocate them per keyframe. One workspace serves one call at a time.
class BundleAdjustmentWorkspace {
 public:
  BundleAdjustmentWorkspace();
  [[nodiscard]] detail::SchurWorkspace* schur() const { return schur_.get(); }

 private:
  std::unique_ptr<detail::SchurWorkspace, detail::SchurWorkspaceDeleter> schur_;
};

// Optimizes the free poses and all observed points of `problem` in place.
// Throws flatslam::Error on out-of-range indices, inv_sigma2 <= 0, stereo without baseline,
// an invalid camera or invalid options.
[[nodiscard]] BundleAdjustmentResult LocalBundleAdjustment(BundleAdjustmentProblem& problem,
                                                           const BundleAdjustmentOptions& options,
                                                           BundleAdjustmentWorkspace* workspace = nullptr);

}  // namespace flatslam
