// Multi-view geometry: two-view DLT triangulation with checks, monocular two-view initialization
// (RANSAC fundamental and homography, model selection, motion recovery), and rigid motion at a
// constant twist.
// Concurrency: stateless free functions; callable from any thread (the caller owns the rng).
#pragma once

#include <optional>
#include <random>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "io/types.h"

namespace flatslam {

// Linear (DLT) triangulation from two 3x4 projection matrices and the matching image points
// in the same units as the matrices (pixels with K[R|t], or normalized with [R|t]).
// nullopt when the solution is at infinity or not finite.
[[nodiscard]] std::optional<Eigen::Vector3d> TriangulateDlt(const Eigen::Matrix<double, 3, 4>& P1,
                                                            const Eigen::Matrix<double, 3, 4>& P2,
                                                            const Eigen::Vector2d& x1, const Eigen::Vector2d& x2);

struct TriangulationOptions {
  double max_reprojection_error_px = 2.0;  // per view, pixels (ORB-SLAM2: error^2 < 4 sigma^2)
  double min_parallax_deg = 1.0;           // angle between the two viewing rays; 0 disables
  double min_depth = 0.0;                  // z in both cameras must exceed this (metres)

  [[nodiscard]] bool Check() const;
};

enum class TriangulationStatus {
  kOk,
  kDegenerate,    // rays parallel or solution at infinity
  kBehindCamera,  // z <= min_depth in either view
  kLargeError,    // reprojection error above the threshold in either view
  kLowParallax,   // viewing rays closer than min_parallax_deg
};

struct TriangulatedPoint {
  Eigen::Vector3d X_world = Eigen::Vector3d::Zero();
  TriangulationStatus status = TriangulationStatus::kDegenerate;
  double parallax_deg = 0;  // angle between the two viewing rays at the point
  double max_error_px = 0;  // larger of the two reprojection errors

  [[nodiscard]] bool ok() const { return status == TriangulationStatus::kOk; }
};

// Triangulates one pixel correspondence seen from two posed cameras and checks depth,
// reprojection error and parallax. X_world is filled whenever the DLT has a finite solution.
[[nodiscard]] TriangulatedPoint TriangulatePoint(const PinholeCamera& camera, const Eigen::Isometry3d& T_cam1_world,
                                                 const Eigen::Isometry3d& T_cam2_world, const Eigen::Vector2d& px1,
                                                 const Eigen::Vector2d& px2, const TriangulationOptions& options);

struct TwoViewOptions {
  int ransac_iterations = 500;                // minimal sets shared by F and H (ORB-SLAM2: 200; our F
                                              // hypotheses are projected to essential ones, so noisier)
  double sigma_px = 1.0;                      // keypoint noise per image (octave 0); model errors use 2 sigma^2
  double chi2_one_dof = 3.841;                // F inlier gate (point-to-epipolar-line, 1 DoF, 95%)
  double chi2_two_dof = 5.991;                // H inlier gate and score ceiling (2 DoF, 95%)
  double homography_ratio = 0.45;             // select H when SH / (SH + SF) exceeds this
  int local_optimization_passes = 4;          // LO-RANSAC: least-squares re-fits of each new best model
  bool homography_fallback = true;            // when SH / (SH + SF) is within ...
  double homography_fallback_ratio = 0.35;    // ... this of 0 and 1, also try the other model
  bool refine_with_bundle_adjustment = true;  // two-view BA of the winning motion and points
  int refine_iterations = 10;                 // per BA pass (robust pass, then inliers only)
  int refine_rounds = 5;                      // BA + re-selection of inliers, until they stop growing
  double max_reprojection_error_px = 2.0;     // triangulation gate per view (2 sigma)
  double min_point_parallax_deg = 0.36;       // a point is triangulated above this parallax
  double min_parallax_deg = 1.0;              // the scene parallax (see parallax_rank) must exceed this
  int parallax_rank = 50;                     // scene parallax = the point parallax at this 0-based rank,
                                              // largest first (robust to a few near points)
  int min_triangulated = 50;                  // fewer good points than this = failure
  double min_good_fraction = 0.9;             // good points must be this fraction of model inliers
  double clear_winner_ratio = 0.75;           // runner-up motion must have fewer good points than this x best

  [[nodiscard]] bool Check() const;
};

struct TwoViewResult {
  Eigen::Isometry3d T_2_1 = Eigen::Isometry3d::Identity();  // maps view-1 coordinates into view 2
  std::vector<Eigen::Vector3d> points;                      // per correspondence, in view-1 coordinates
  std::vector<bool> triangulated;                           // per correspondence: points[i] is valid
  // Correspondences consistent with the selected model, or with the refined motion's epipolar
  // geometry when that is more.
  int inliers = 0;
  bool used_homography = false;
  int num_triangulated = 0;     // count of triangulated[i] == true
  double parallax_deg = 0;      // scene parallax that passed min_parallax_deg
  double homography_ratio = 0;  // SH / (SH + SF)
};

// Monocular initialization from matched pixels px1[i] <-> px2[i] (undistorted):
//  1. RANSAC on shared 8-point sets: H by 4-point DLT (first 4), F by the normalized 8-point
//     algorithm projected onto the essential manifold; symmetric transfer / epipolar scores with
//     chi2 gating; each new best model is re-fitted on its consensus set (LO-RANSAC).
//  2. H if RH = SH / (SH + SF) > homography_ratio, else F (and H too in the fallback band).
//  3. Candidate motions (4 from E = K^T F K, up to 4 from H); the one with the most points in
//     front and reprojecting well wins if clearly ahead of the runner-up.
//  4. Two-view BA refines the motion; inliers are re-selected with it and re-triangulated.
// Scale is fixed so the median depth of the triangulated points in view 1 is 1. nullopt when the
// motion is ambiguous (no clear winner, e.g. the two-fold ambiguity of a plane), parallax is too
// low (e.g. pure rotation) or too few points survive. Deterministic given rng's state.
// Throws flatslam::Error when the two vectors differ in size or the options are invalid.
[[nodiscard]] std::optional<TwoViewResult> InitializeTwoView(const std::vector<Eigen::Vector2d>& px1,
                                                             const std::vector<Eigen::Vector2d>& px2,
                                                             const PinholeCamera& camera, const TwoViewOptions& options,
                                                             std::mt19937_64& rng);

// The rigid motion T continued at its constant twist for s times as long: exp(s log T) in SE(3)
// (s = 2 gives T * T, s = 0.5 the motion whose square is T, s = 0 the identity). Rotations of
// T up to pi.
[[nodiscard]] Eigen::Isometry3d ScaledMotion(const Eigen::Isometry3d& T, double s);

}  // namespace flatslam
