// Similarity transforms (rotation, translation, scale) for loop closure: closed-form alignment
// of 3D-3D correspondences, RANSAC over keyframe matches with a reprojection test in both
// cameras (Sim(3) for monocular maps, SE(3) with scale fixed to 1 for stereo/RGB-D), and an
// essential-graph optimization over keyframe poses with Ceres.
// Concurrency: pure functions; each call is single-threaded.
#pragma once

#include <algorithm>
#include <cstdint>
#include <optional>
#include <random>
#include <span>
#include <unordered_set>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "ecs/map.h"
#include "io/types.h"

namespace flatslam {

// X' = s R X + t.
struct Similarity3 {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  double s = 1.0;

  [[nodiscard]] static Similarity3 FromIsometry(const Eigen::Isometry3d& T) {
    return {T.linear(), T.translation(), 1.0};
  }
  // The rigid part with the translation divided by the scale (the camera pose a Sim(3) of a
  // camera implies: same center, same orientation).
  [[nodiscard]] Eigen::Isometry3d ToIsometry() const;
  [[nodiscard]] Eigen::Vector3d operator*(const Eigen::Vector3d& X) const { return s * (R * X) + t; }
  [[nodiscard]] Similarity3 operator*(const Similarity3& o) const { return {R * o.R, s * (R * o.t) + t, s * o.s}; }
  [[nodiscard]] Similarity3 inverse() const {
    const Eigen::Matrix3d Rt = R.transpose();
    return {Rt, -(Rt * t) / s, 1.0 / s};
  }
  // [R|t] with the scale left out (X_new = s * (R X) + t = RigidPart() * (s X)): the form
  // Map::MoveFrame and MovedCameraPose take, beside s.
  [[nodiscard]] Eigen::Isometry3d RigidPart() const {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = R;
    T.translation() = t;
    return T;
  }
};

// A camera pose after its world moved by S (ecs/map.h's MovedCameraPose).
[[nodiscard]] inline Eigen::Isometry3d MovedCameraPose(const Eigen::Isometry3d& T_cam_world, const Similarity3& S) {
  return MovedCameraPose(T_cam_world, S.RigidPart(), S.s);
}

// Least-squares S with X2 ~ S * X1 (Umeyama). nullopt for fewer than 3 points or a degenerate set.
[[nodiscard]] std::optional<Similarity3> AlignPoints(std::span<const Eigen::Vector3d> X1,
                                                     std::span<const Eigen::Vector3d> X2, bool fix_scale);

// A putative match between two keyframes: the point of keyframe 1 in camera-1 coordinates and
// the one of keyframe 2 in camera-2 coordinates, with the pixels that observed them.
struct PointCorrespondence {
  Eigen::Vector3d X1, X2;
  Eigen::Vector2d uv1, uv2;
  float sigma2_1 = 1, sigma2_2 = 1;  // scale_factor^(2 octave) of each keypoint
};

struct SimilarityRansacOptions {
  int iterations = 300;
  int min_inliers = 20;
  double chi2 = 9.210;  // per image, 2 DoF at 99%
  bool fix_scale = false;

  [[nodiscard]] bool Check() const { return iterations > 0 && min_inliers >= 3 && chi2 > 0; }
};

struct SimilarityRansacResult {
  Similarity3 S_21;  // camera 1 -> camera 2
  std::vector<bool> inlier;
  int num_inliers = 0;
};

// RANSAC on minimal sets of three, then a refit on all inliers. A correspondence is an inlier
// when it reprojects within chi2 * sigma2 in both images. nullopt when fewer than min_inliers.
[[nodiscard]] std::optional<SimilarityRansacResult> EstimateSimilarityRansac(
    const PinholeCamera& camera, std::span<const PointCorrespondence> matches, const SimilarityRansacOptions& options,
    std::mt19937_64& rng);

// Essential graph: nodes are keyframe poses S_cw (world -> camera, scale 1 before optimization),
// edges measured relative transforms S_ij = S_i * S_j^-1.
struct PoseGraphEdge {
  uint32_t i = 0, j = 0;
  Similarity3 S_ij;
  double weight = 1.0;
};

// Edges of an essential graph, each node pair at most once (the first measurement wins).
class PoseGraphEdgeSet {
 public:
  void Add(uint32_t i, uint32_t j, const Similarity3& S_ij) {
    if (i == j) return;
    const uint64_t key = (uint64_t{std::min(i, j)} << 32) | std::max(i, j);
    if (have_.insert(key).second) edges_.push_back({i, j, S_ij, 1.0});
  }
  [[nodiscard]] const std::vector<PoseGraphEdge>& edges() const { return edges_; }

 private:
  std::vector<PoseGraphEdge> edges_;
  std::unordered_set<uint64_t> have_;
};

struct PoseGraphOptions {
  int iterations = 20;
  bool fix_scale = false;  // SE(3) graph (stereo/RGB-D)
  int num_threads = 1;     // Ceres' residual and Jacobian evaluation
};

// Optimizes the free nodes of S_cw in place (fixed[i] holds node i). Returns the final cost.
double OptimizePoseGraph(std::vector<Similarity3>& S_cw, const std::vector<bool>& fixed,
                         std::span<const PoseGraphEdge> edges, const PoseGraphOptions& options);

}  // namespace flatslam
