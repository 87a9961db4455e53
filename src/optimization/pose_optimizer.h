// Pose-only optimization: refines T_cam_world from 3D-2D (mono) and 3D-stereo observations
// with a robust Huber loss and chi-square outlier rejection over several rounds (Ceres).
// Concurrency: stateless free functions; callable from any thread, each call is single-threaded.
#pragma once

#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "core/option_fields.h"
#include "optimization/outlier_gates.h"

#include "io/types.h"

namespace ceres {
class Manifold;
}

namespace flatslam {

// One map point seen in the frame being optimized.
struct PoseObservation {
  Eigen::Vector3d X_world = Eigen::Vector3d::Zero();
  Eigen::Vector2d uv = Eigen::Vector2d::Zero();  // left-image pixel, undistorted
  double right_u = -1;                           // rectified right-image x; < 0 = mono observation
  float inv_sigma2 = 1.0f;                       // 1 / scale_factor^(2 octave)
};

// Pose optimization's options: X(type, name, default, requirement, description) (core/option_fields.h).
#define FLATSLAM_POSE_OPTIONS(X)                                                                           \
  X(int, rounds, 4, rounds >= 1, "optimize / classify rounds")                                             \
  X(int, iterations_per_round, 10, iterations_per_round >= 1, "Levenberg-Marquardt iterations per round")  \
  FLATSLAM_OUTLIER_GATE_OPTIONS(X)                                                                         \
  X(bool, robust_last_round, false, true, "keep the robust kernel in the last round (ORB-SLAM2 drops it)") \
  X(int, min_observations, 3, min_observations >= 0, "fewer active observations = failure")

struct PoseOptimizerOptions {
  FLATSLAM_POSE_OPTIONS(FLATSLAM_OPTION_FIELD)

  FLATSLAM_OPTION_MEMBERS(FLATSLAM_POSE_OPTIONS)
  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const { return FieldsProblem(); }
  [[nodiscard]] bool Check() const { return Problem().empty(); }
};

struct PoseOptimizationResult {
  Eigen::Isometry3d T_cam_world = Eigen::Isometry3d::Identity();
  std::vector<bool> inlier;  // per observation, after the last round
  int num_inliers = 0;
  bool success = false;  // false: too few observations or the solver failed;
                         // T_cam_world is then the initial pose
};

// Refines T_cam_world_initial. baseline_m is used for stereo observations only (may be 0 when
// all are mono). Throws flatslam::Error on invalid options or camera; numerical failure is
// reported in success.
[[nodiscard]] PoseOptimizationResult OptimizePose(const PinholeCamera& camera, double baseline_m,
                                                  const Eigen::Isometry3d& T_cam_world_initial,
                                                  const std::vector<PoseObservation>& observations,
                                                  const PoseOptimizerOptions& options);

namespace detail {
// Pose parameter block shared with bundle adjustment: [qx qy qz qw tx ty tz] of T_cam_world.
inline constexpr int kPoseParameterSize = 7;
void PoseToParameters(const Eigen::Isometry3d& T_cam_world, double* parameters);
[[nodiscard]] Eigen::Isometry3d ParametersToPose(const double* parameters);
// Left perturbation T <- Exp(delta) T with delta = [rotation(3), translation(3)]. Cost functions
// write their Jacobian w.r.t. delta into the first 6 columns of the 7-column block (7th = 0).
[[nodiscard]] std::unique_ptr<ceres::Manifold> MakePoseManifold();
}  // namespace detail

}  // namespace flatslam
