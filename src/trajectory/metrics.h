// Trajectory evaluation: timestamp association, Umeyama alignment, ATE, RPE and the KITTI
// odometry segment metric, matching evo and the KITTI devkit.
// Concurrency: stateless free functions on values, callable from any thread.
#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string_view>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "trajectory/trajectory.h"

namespace flatslam {

// ---- Association ----

// A matched pose: gt[gt_index] and est[est_index] are taken at (about) the same time.
struct IndexPair {
  size_t gt_index = 0;
  size_t est_index = 0;
};

struct AssociationOptions {
  // Largest |t_gt - t_est| accepted, inclusive; evo's --t_max_diff (20 ms here).
  double max_diff_s = 0.02;
  // Added to the estimate's timestamps before matching (evo's --t_offset).
  double est_offset_s = 0.0;

  [[nodiscard]] bool Check() const;
};

// As evo's associate_trajectories: for each pose of the shorter trajectory (the estimate
// when both have the same length) the nearest timestamp of the longer one, first on ties;
// kept when within max_diff_s. A pose of the longer trajectory may be used twice. Pairs
// come in the order of the shorter trajectory. Throws flatslam::Error on empty input.
[[nodiscard]] std::vector<IndexPair> AssociateByTime(const Trajectory& gt, const Trajectory& est,
                                                     const AssociationOptions& options = {});
// Pairs pose i with pose i; throws flatslam::Error when the lengths differ.
[[nodiscard]] std::vector<IndexPair> AssociateByIndex(const Trajectory& gt, const Trajectory& est);

// ---- Alignment ----

enum class Alignment {
  kNone,  // compare as given
  kSE3,   // rotation + translation (stereo, RGB-D, visual-inertial)
  kSim3,  // rotation + translation + scale (monocular)
};

// "none", "se3" or "sim3".
[[nodiscard]] const char* AlignmentName(Alignment alignment);
[[nodiscard]] std::optional<Alignment> ParseAlignment(std::string_view name);

// The similarity p_gt = scale * R * p_est + t that best maps estimate positions onto ground truth.
struct AlignmentResult {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  double scale = 1.0;
  // False when no finite similarity exists (no positions, or Sim(3) of an estimate whose
  // positions are all equal); the transform is then the identity. A value, not an exception.
  bool valid = true;

  // Applies the similarity to a pose: rotation R*R_est, position scale*R*p_est + t.
  [[nodiscard]] Eigen::Isometry3d Apply(const Eigen::Isometry3d& T_world_cam) const;
};

// Umeyama least squares (Eigen::umeyama) of est_positions onto gt_positions, same length.
[[nodiscard]] AlignmentResult AlignUmeyama(const std::vector<Eigen::Vector3d>& gt_positions,
                                           const std::vector<Eigen::Vector3d>& est_positions, Alignment alignment);

// ---- Error statistics ----

struct ErrorStats {
  size_t count = 0;  // 0: no samples, all other fields are 0
  double rmse = 0, mean = 0, median = 0, std = 0, min = 0, max = 0;
};

// Summary of errors; std is the population standard deviation and median averages the two
// middle values for an even count (as numpy).
[[nodiscard]] ErrorStats ComputeErrorStats(std::vector<double> errors);

// ---- Metrics on matched poses (gt[i] and est[i] belong together, est already aligned) ----

// Absolute trajectory error: per-pair distance between positions, in metres.
[[nodiscard]] ErrorStats ComputeAte(const std::vector<Eigen::Isometry3d>& gt,
                                    const std::vector<Eigen::Isometry3d>& est);

struct RpeResult {
  size_t pairs = 0;          // number of (i, j) pose pairs compared
  ErrorStats translation_m;  // |t| of E = (gt_i^-1 gt_j)^-1 (est_i^-1 est_j)
  ErrorStats rotation_deg;   // rotation angle of E
};

// RPE over pairs (i, i+delta), (i+delta, i+2 delta), ... starting at 0 (evo without --all_pairs).
[[nodiscard]] RpeResult ComputeRpeFrames(const std::vector<Eigen::Isometry3d>& gt,
                                         const std::vector<Eigen::Isometry3d>& est, size_t delta_frames);
// RPE over consecutive pairs (i, j) where j is the first pose at least delta_m further along
// the ground-truth path than i, then from j on.
[[nodiscard]] RpeResult ComputeRpeDistance(const std::vector<Eigen::Isometry3d>& gt,
                                           const std::vector<Eigen::Isometry3d>& est, double delta_m);

struct KittiMetricOptions {
  // Segment lengths in metres, as the KITTI odometry devkit.
  std::vector<double> lengths_m = {100, 200, 300, 400, 500, 600, 700, 800};
  // A segment starts every step_frames frames (devkit: 10).
  size_t step_frames = 10;

  [[nodiscard]] bool Check() const;
};

struct KittiMetricResult {
  // False when no segment fits (ground-truth path shorter than the shortest length).
  bool available = false;
  size_t segments = 0;
  double path_length_m = 0;       // length of the ground-truth path
  double t_rel_percent = 0;       // mean over segments of t_err / length, in %
  double r_rel_deg_per_100m = 0;  // mean over segments of r_err / length, in deg per 100 m
};

// The KITTI odometry devkit's metric: for each start frame (every step_frames) and length L,
// the first frame j with path(j) > path(start) + L; error of the relative pose over L.
[[nodiscard]] KittiMetricResult ComputeKittiMetric(const std::vector<Eigen::Isometry3d>& gt,
                                                   const std::vector<Eigen::Isometry3d>& est,
                                                   const KittiMetricOptions& options = {});

// Rotation angle of a rotation matrix in radians, accurate near 0 and pi.
[[nodiscard]] double RotationAngle(const Eigen::Matrix3d& rotation);

// ---- Everything at once ----

struct EvalOptions {
  AssociationOptions association;
  // Pair pose i with pose i instead of by time (KITTI files without timestamps).
  bool pair_by_index = false;
  // Alignment of the estimate onto ground truth before every metric.
  Alignment alignment = Alignment::kSE3;
  // RPE frame step (1 = consecutive poses).
  size_t rpe_delta_frames = 1;
  // RPE distance step along the ground-truth path, metres.
  double rpe_delta_m = 1.0;
  KittiMetricOptions kitti;

  [[nodiscard]] bool Check() const;
};

struct EvalResult {
  std::vector<IndexPair> pairs;
  AlignmentResult alignment;
  ErrorStats ate_m;
  RpeResult rpe_frames;
  RpeResult rpe_distance;
  KittiMetricResult kitti;
};

// Associates, aligns and computes every metric. Throws flatslam::Error when no pose pairs
// match or the alignment is degenerate.
[[nodiscard]] EvalResult Evaluate(const Trajectory& gt, const Trajectory& est, const EvalOptions& options = {});

// Several estimates in one frame (the agents of a merged map), each against its own ground truth
// (associated within the pair, by time or index as options say), under ONE alignment of all of
// them: a per-pair alignment would hide an estimate misplaced in the shared frame.
struct JointAteResult {
  AlignmentResult alignment;          // of every pair's positions together
  std::vector<size_t> pairs;          // pose pairs per estimate
  std::vector<ErrorStats> ate_m;      // per estimate, under the one alignment
  std::vector<ErrorStats> own_ate_m;  // per estimate, aligned alone (options.alignment)
  ErrorStats all_m;                   // every pair together
};
// Throws flatslam::Error naming the estimate that has no pose pairs, or when the positions do not
// spread enough to align.
[[nodiscard]] JointAteResult EvaluateJointAte(const std::vector<Trajectory>& gt, const std::vector<Trajectory>& est,
                                              const EvalOptions& options = {});

}  // namespace flatslam
