#include "geometry/geometry.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <limits>
#include <numeric>

#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#include <Eigen/QR>
#include <Eigen/SVD>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>

#include "core/error.h"
#include "geometry/camera.h"
#include "optimization/bundle_adjustment.h"

namespace flatslam {
namespace {

constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;

using Matrix34d = Eigen::Matrix<double, 3, 4>;

// Angle in degrees between the rays from c1 and c2 towards X.
double ParallaxDeg(const Eigen::Vector3d& X, const Eigen::Vector3d& c1, const Eigen::Vector3d& c2) {
  const Eigen::Vector3d r1 = X - c1;
  const Eigen::Vector3d r2 = X - c2;
  const double denom = r1.norm() * r2.norm();
  if (denom <= 0) return 0;
  const double cos_angle = std::clamp(r1.dot(r2) / denom, -1.0, 1.0);
  return std::acos(cos_angle) * kRadToDeg;
}

// Squared pixel error of projecting camera-frame point x_cam; infinite behind the image plane.
double ReprojectionError2(const Eigen::Matrix3d& K, const Eigen::Vector3d& x_cam, const Eigen::Vector2d& px) {
  if (x_cam.z() == 0) return std::numeric_limits<double>::infinity();
  const double inv_z = 1.0 / x_cam.z();
  const double u = K(0, 0) * x_cam.x() * inv_z + K(0, 2);
  const double v = K(1, 1) * x_cam.y() * inv_z + K(1, 2);
  return (Eigen::Vector2d(u, v) - px).squaredNorm();
}

// Hartley normalization: centroid to origin, mean distance sqrt(2). Returns the 3x3 transform.
Eigen::Matrix3d Normalize(const std::vector<Eigen::Vector2d>& px, std::vector<Eigen::Vector2d>* out) {
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  for (const auto& p : px) mean += p;
  mean /= static_cast<double>(std::max<size_t>(px.size(), 1));
  double mean_dist = 0;
  for (const auto& p : px) mean_dist += (p - mean).norm();
  mean_dist /= static_cast<double>(std::max<size_t>(px.size(), 1));
  const double s = mean_dist > 0 ? std::sqrt(2.0) / mean_dist : 1.0;
  out->resize(px.size());
  for (size_t i = 0; i < px.size(); ++i) (*out)[i] = s * (px[i] - mean);
  Eigen::Matrix3d T;
  T << s, 0, -s * mean.x(), 0, s, -s * mean.y(), 0, 0, 1;
  return T;
}

using DltRows = Eigen::Matrix<double, Eigen::Dynamic, 9>;

// Unit vector h minimizing |A h|, reshaped row-major into 3x3. Fewer than 9 rows (a minimal
// set): the null space from a QR of A^T, which is exact and cheap; otherwise the eigenvector of
// the smallest eigenvalue of A^T A (least squares over a consensus set).
Eigen::Matrix3d SmallestNullVector(const DltRows& A) {
  Eigen::Matrix<double, 9, 1> h;
  if (A.rows() < 9) {
    const Eigen::HouseholderQR<Eigen::Matrix<double, 9, Eigen::Dynamic>> qr(A.transpose());
    h = qr.householderQ() * Eigen::Matrix<double, 9, 1>::Unit(8);
  } else {
    const Eigen::Matrix<double, 9, 9> AtA = A.transpose() * A;
    h = Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 9, 9>>(AtA).eigenvectors().col(0);
  }
  Eigen::Matrix3d M;
  M << h(0), h(1), h(2), h(3), h(4), h(5), h(6), h(7), h(8);
  return M;
}

// Homography x2 ~ H x1 from normalized points via DLT over the given indices (4 = minimal).
Eigen::Matrix3d FitHomography(const std::vector<Eigen::Vector2d>& x1, const std::vector<Eigen::Vector2d>& x2,
                              const int* idx, int count) {
  DltRows A(2 * count, 9);
  for (int k = 0; k < count; ++k) {
    const int i = idx[k];
    const double u1 = x1[i].x(), v1 = x1[i].y(), u2 = x2[i].x(), v2 = x2[i].y();
    A.row(2 * k) << 0, 0, 0, -u1, -v1, -1, v2 * u1, v2 * v1, v2;
    A.row(2 * k + 1) << u1, v1, 1, 0, 0, 0, -u2 * u1, -u2 * v1, -u2;
  }
  return SmallestNullVector(A);
}

// Fundamental matrix x2^T F x1 = 0 from normalized points (8 = minimal), rank 2 enforced.
Eigen::Matrix3d FitFundamental(const std::vector<Eigen::Vector2d>& x1, const std::vector<Eigen::Vector2d>& x2,
                               const int* idx, int count) {
  DltRows A(count, 9);
  for (int k = 0; k < count; ++k) {
    const int i = idx[k];
    const double u1 = x1[i].x(), v1 = x1[i].y(), u2 = x2[i].x(), v2 = x2[i].y();
    A.row(k) << u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, 1;
  }
  const Eigen::Matrix3d F = SmallestNullVector(A);
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Vector3d sv = svd.singularValues();
  sv(2) = 0;
  return svd.matrixU() * sv.asDiagonal() * svd.matrixV().transpose();
}

struct ModelScore {
  double score = 0;
  std::vector<bool> inlier;
  int num_inliers = 0;
};

// Symmetric transfer score of H (pixels): each direction adds (gate - chi2) when under the gate.
void ScoreHomography(const Eigen::Matrix3d& H21, const std::vector<Eigen::Vector2d>& px1,
                     const std::vector<Eigen::Vector2d>& px2, double inv_sigma2, double gate, ModelScore* out) {
  const size_t n = px1.size();
  out->score = 0;
  out->num_inliers = 0;
  out->inlier.assign(n, false);
  const Eigen::FullPivLU<Eigen::Matrix3d> lu(H21);
  if (!lu.isInvertible()) return;
  const Eigen::Matrix3d H12 = lu.inverse();
  const Eigen::Matrix3d& H = H21;
  for (size_t i = 0; i < n; ++i) {
    const double u1 = px1[i].x(), v1 = px1[i].y(), u2 = px2[i].x(), v2 = px2[i].y();
    const double w2 = H(2, 0) * u1 + H(2, 1) * v1 + H(2, 2);
    if (w2 == 0) continue;
    const double du2 = (H(0, 0) * u1 + H(0, 1) * v1 + H(0, 2)) / w2 - u2;
    const double dv2 = (H(1, 0) * u1 + H(1, 1) * v1 + H(1, 2)) / w2 - v2;
    const double chi2_in2 = (du2 * du2 + dv2 * dv2) * inv_sigma2;
    if (!(chi2_in2 <= gate)) continue;
    const double w1 = H12(2, 0) * u2 + H12(2, 1) * v2 + H12(2, 2);
    if (w1 == 0) continue;
    const double du1 = (H12(0, 0) * u2 + H12(0, 1) * v2 + H12(0, 2)) / w1 - u1;
    const double dv1 = (H12(1, 0) * u2 + H12(1, 1) * v2 + H12(1, 2)) / w1 - v1;
    const double chi2_in1 = (du1 * du1 + dv1 * dv1) * inv_sigma2;
    if (!(chi2_in1 <= gate)) continue;
    out->score += (gate - chi2_in2) + (gate - chi2_in1);
    out->inlier[i] = true;
    ++out->num_inliers;
  }
}

// Symmetric epipolar score of F (pixels): distance to the epipolar line in both images,
// gated at 1 DoF and scored against the 2 DoF ceiling so H and F scores are comparable.
void ScoreFundamental(const Eigen::Matrix3d& F21, const std::vector<Eigen::Vector2d>& px1,
                      const std::vector<Eigen::Vector2d>& px2, double inv_sigma2, double gate, double score_ceiling,
                      ModelScore* out) {
  const size_t n = px1.size();
  out->score = 0;
  out->num_inliers = 0;
  out->inlier.assign(n, false);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d x1 = px1[i].homogeneous();
    const Eigen::Vector3d x2 = px2[i].homogeneous();
    const Eigen::Vector3d l2 = F21 * x1;
    const Eigen::Vector3d l1 = F21.transpose() * x2;
    const double n2 = l2.head<2>().squaredNorm();
    const double n1 = l1.head<2>().squaredNorm();
    if (n1 <= 0 || n2 <= 0) continue;
    const double e2 = l2.dot(x2);
    const double e1 = l1.dot(x1);
    const double chi2_in2 = e2 * e2 / n2 * inv_sigma2;
    const double chi2_in1 = e1 * e1 / n1 * inv_sigma2;
    if (!(chi2_in2 <= gate) || !(chi2_in1 <= gate)) continue;
    out->score += (score_ceiling - chi2_in2) + (score_ceiling - chi2_in1);
    out->inlier[i] = true;
    ++out->num_inliers;
  }
}

std::vector<int> InlierIndices(const std::vector<bool>& inlier) {
  std::vector<int> idx;
  for (size_t i = 0; i < inlier.size(); ++i)
    if (inlier[i]) idx.push_back(static_cast<int>(i));
  return idx;
}

struct Motion {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
};

// Outcome of triangulating the model inliers under one candidate motion.
struct MotionCheck {
  int good = 0;             // in front (where measurable) and reprojecting well
  double parallax_deg = 0;  // scene parallax at the configured rank
  std::vector<Eigen::Vector3d> points;
  std::vector<bool> triangulated;
};

MotionCheck CheckMotion(const Motion& motion, const std::vector<Eigen::Vector2d>& px1,
                        const std::vector<Eigen::Vector2d>& px2, const std::vector<bool>& inlier,
                        const PinholeCamera& camera, const TwoViewOptions& options) {
  const size_t n = px1.size();
  MotionCheck out;
  out.points.assign(n, Eigen::Vector3d::Zero());
  out.triangulated.assign(n, false);
  const Eigen::Matrix3d K = camera.K();
  Matrix34d P1 = Matrix34d::Zero();
  P1.leftCols<3>().setIdentity();
  Matrix34d P2;
  P2.leftCols<3>() = motion.R;
  P2.col(3) = motion.t;
  const Eigen::Vector3d c1 = Eigen::Vector3d::Zero();
  const Eigen::Vector3d c2 = -motion.R.transpose() * motion.t;
  const double max_err2 = options.max_reprojection_error_px * options.max_reprojection_error_px;
  const double min_point_parallax = options.min_point_parallax_deg;
  std::vector<double> parallaxes;
  parallaxes.reserve(n);
  for (size_t i = 0; i < n; ++i) {
    if (!inlier[i]) continue;
    const Eigen::Vector2d x1((px1[i].x() - camera.cx) / camera.fx, (px1[i].y() - camera.cy) / camera.fy);
    const Eigen::Vector2d x2((px2[i].x() - camera.cx) / camera.fx, (px2[i].y() - camera.cy) / camera.fy);
    const std::optional<Eigen::Vector3d> X = TriangulateDlt(P1, P2, x1, x2);
    if (!X) continue;
    const double parallax = ParallaxDeg(*X, c1, c2);
    const bool measurable = parallax > min_point_parallax;
    const Eigen::Vector3d X2 = motion.R * *X + motion.t;
    // Depth sign is meaningless for near-parallel rays; only reject it where it is measurable.
    if (measurable && (X->z() <= 0 || X2.z() <= 0)) continue;
    if (!(ReprojectionError2(K, *X, px1[i]) <= max_err2)) continue;
    if (!(ReprojectionError2(K, X2, px2[i]) <= max_err2)) continue;
    ++out.good;
    parallaxes.push_back(parallax);
    if (measurable) {
      out.points[i] = *X;
      out.triangulated[i] = true;
    }
  }
  if (!parallaxes.empty()) {
    std::sort(parallaxes.begin(), parallaxes.end(), std::greater<double>());
    const size_t rank = std::min<size_t>(static_cast<size_t>(options.parallax_rank), parallaxes.size() - 1);
    out.parallax_deg = parallaxes[rank];
  }
  return out;
}

// The four (R, t) factorizations of an essential matrix, |t| = 1.
std::vector<Motion> MotionsFromEssential(const Eigen::Matrix3d& E) {
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(E, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d& U = svd.matrixU();
  const Eigen::Matrix3d& V = svd.matrixV();
  Eigen::Matrix3d W;
  W << 0, -1, 0, 1, 0, 0, 0, 0, 1;
  Eigen::Matrix3d Ra = U * W * V.transpose();
  Eigen::Matrix3d Rb = U * W.transpose() * V.transpose();
  if (Ra.determinant() < 0) Ra = -Ra;
  if (Rb.determinant() < 0) Rb = -Rb;
  const Eigen::Vector3d t = U.col(2).normalized();
  return {{Ra, t}, {Ra, -t}, {Rb, t}, {Rb, -t}};
}

// Candidate motions of a pixel homography (Malis-Vargas decomposition in OpenCV).
std::vector<Motion> MotionsFromHomography(const Eigen::Matrix3d& H21, const Eigen::Matrix3d& K) {
  cv::Mat H_cv, K_cv;
  cv::eigen2cv(H21, H_cv);
  cv::eigen2cv(K, K_cv);
  std::vector<cv::Mat> rotations, translations, normals;
  cv::decomposeHomographyMat(H_cv, K_cv, rotations, translations, normals);
  std::vector<Motion> motions;
  for (size_t k = 0; k < rotations.size(); ++k) {
    Motion m;
    cv::cv2eigen(rotations[k], m.R);
    cv::cv2eigen(translations[k], m.t);
    if (!m.R.allFinite() || !m.t.allFinite()) continue;
    motions.push_back(m);
  }
  return motions;
}

// Transfer and epipolar errors difference two noisy keypoints: their variance is 2 sigma^2.
double ModelInvSigma2(const TwoViewOptions& options) {
  return 1.0 / (2.0 * options.sigma_px * options.sigma_px);
}

// Picks k distinct indices of [0, n) with a partial Fisher-Yates shuffle of *pool.
void SampleIndices(int k, std::vector<int>* pool, std::mt19937_64& rng, std::vector<int>* out) {
  const int n = static_cast<int>(pool->size());
  out->resize(k);
  for (int j = 0; j < k; ++j) {
    std::uniform_int_distribution<int> pick(j, n - 1);
    std::swap((*pool)[j], (*pool)[pick(rng)]);
    (*out)[j] = (*pool)[j];
  }
}

// A motion that won the candidate test, with its triangulated inliers (view-1 frame).
struct Reconstruction {
  Motion motion;
  std::vector<Eigen::Vector3d> points;
  std::vector<bool> triangulated;
  int inliers = 0;
  int good = 0;
  double parallax_deg = 0;
};

// Refines a motion by two-view bundle adjustment over every correspondence in `use` that the
// current motion places in front of both cameras (the robust loss and chi2 test, not a pixel
// gate, sort them). View 1 is fixed; the scale gauge is left to the median-depth normalization.
// false when the solver fails.
bool RefineTwoView(const std::vector<Eigen::Vector2d>& px1, const std::vector<Eigen::Vector2d>& px2,
                   const std::vector<bool>& use, const PinholeCamera& camera, const TwoViewOptions& options,
                   Motion* motion) {
  BundleAdjustmentProblem ba;
  ba.camera = camera;
  Eigen::Isometry3d T_2_1 = Eigen::Isometry3d::Identity();
  T_2_1.linear() = motion->R;
  T_2_1.translation() = motion->t;
  ba.poses = {{Eigen::Isometry3d::Identity(), true}, {T_2_1, false}};
  Matrix34d P1 = Matrix34d::Zero();
  P1.leftCols<3>().setIdentity();
  const Matrix34d P2 = T_2_1.matrix().topRows<3>();
  const float inv_sigma2 = static_cast<float>(1.0 / (options.sigma_px * options.sigma_px));
  for (size_t i = 0; i < use.size(); ++i) {
    if (!use[i]) continue;
    const Eigen::Vector2d x1((px1[i].x() - camera.cx) / camera.fx, (px1[i].y() - camera.cy) / camera.fy);
    const Eigen::Vector2d x2((px2[i].x() - camera.cx) / camera.fx, (px2[i].y() - camera.cy) / camera.fy);
    const std::optional<Eigen::Vector3d> X = TriangulateDlt(P1, P2, x1, x2);
    if (!X || X->z() <= 0 || (T_2_1 * *X).z() <= 0) continue;
    const auto point = static_cast<uint32_t>(ba.points.size());
    ba.points.push_back(*X);
    BundleAdjustmentObservation obs;
    obs.point_index = point;
    obs.inv_sigma2 = inv_sigma2;
    obs.pose_index = 0;
    obs.uv = px1[i];
    ba.observations.push_back(obs);
    obs.pose_index = 1;
    obs.uv = px2[i];
    ba.observations.push_back(obs);
  }
  if (ba.points.empty()) return false;
  BundleAdjustmentOptions ba_options;
  ba_options.first_pass_iterations = options.refine_iterations;
  ba_options.second_pass_iterations = options.refine_iterations;
  const BundleAdjustmentResult result = LocalBundleAdjustment(ba, ba_options);
  if (!result.success || !ba.poses[1].T_cam_world.matrix().allFinite()) return false;
  motion->R = ba.poses[1].T_cam_world.linear();
  motion->t = ba.poses[1].T_cam_world.translation();
  return motion->t.norm() > 0;
}

// Picks the candidate motion with the most good points (nullopt without a clear winner),
// optionally refines it by two-view BA and re-triangulates, then checks support and parallax.
std::optional<Reconstruction> Reconstruct(const std::vector<Motion>& motions, const ModelScore& model,
                                          const std::vector<Eigen::Vector2d>& px1,
                                          const std::vector<Eigen::Vector2d>& px2, const PinholeCamera& camera,
                                          const TwoViewOptions& options) {
  if (motions.empty() || model.num_inliers < 8) return std::nullopt;
  int best = -1, best_good = -1, second_good = 0;
  std::vector<MotionCheck> checks;
  checks.reserve(motions.size());
  for (const Motion& m : motions) {
    checks.push_back(CheckMotion(m, px1, px2, model.inlier, camera, options));
    const int good = checks.back().good;
    if (good > best_good) {
      second_good = std::max(second_good, best_good);
      best_good = good;
      best = static_cast<int>(checks.size()) - 1;
    } else {
      second_good = std::max(second_good, good);
    }
  }
  if (best_good < std::max(options.min_triangulated, 1)) return std::nullopt;
  if (second_good >= options.clear_winner_ratio * best_good) return std::nullopt;
  if (checks[best].parallax_deg < options.min_parallax_deg) return std::nullopt;
  Reconstruction rec;
  rec.motion = motions[best];
  rec.inliers = model.num_inliers;
  MotionCheck* final_check = &checks[best];
  MotionCheck recheck;
  if (options.refine_with_bundle_adjustment) {
    const Eigen::Matrix3d K_inv = camera.K().inverse();
    std::vector<bool> use = model.inlier;
    int previous_inliers = -1;
    for (int round = 0; round < options.refine_rounds; ++round) {
      if (!RefineTwoView(px1, px2, use, camera, options, &rec.motion)) break;
      // The refined motion decides inliers, support and parallax; the linear model only seeded it.
      Eigen::Matrix3d t_skew;
      t_skew << 0, -rec.motion.t.z(), rec.motion.t.y(), rec.motion.t.z(), 0, -rec.motion.t.x(), -rec.motion.t.y(),
          rec.motion.t.x(), 0;
      const Eigen::Matrix3d F21 = K_inv.transpose() * t_skew * rec.motion.R * K_inv;
      ModelScore refined;
      ScoreFundamental(F21, px1, px2, ModelInvSigma2(options), options.chi2_one_dof, options.chi2_two_dof, &refined);
      recheck = CheckMotion(rec.motion, px1, px2, refined.inlier, camera, options);
      final_check = &recheck;
      rec.inliers = std::max(model.num_inliers, refined.num_inliers);
      if (refined.num_inliers <= previous_inliers) break;  // the consensus stopped growing
      previous_inliers = refined.num_inliers;
      use = std::move(refined.inlier);
    }
  }
  const double min_good = std::max<double>(options.min_good_fraction * rec.inliers, options.min_triangulated);
  if (final_check->good < min_good) return std::nullopt;
  if (final_check->parallax_deg < options.min_parallax_deg) return std::nullopt;
  rec.points = std::move(final_check->points);
  rec.triangulated = std::move(final_check->triangulated);
  rec.parallax_deg = final_check->parallax_deg;
  rec.good = final_check->good;
  return rec;
}

}  // namespace

std::optional<Eigen::Vector3d> TriangulateDlt(const Matrix34d& P1, const Matrix34d& P2, const Eigen::Vector2d& x1,
                                              const Eigen::Vector2d& x2) {
  // Rows of A [X; 1] = 0, each scaled to unit length; solved for X by column-pivoting QR.
  Eigen::Matrix4d A;
  A.row(0) = x1.x() * P1.row(2) - P1.row(0);
  A.row(1) = x1.y() * P1.row(2) - P1.row(1);
  A.row(2) = x2.x() * P2.row(2) - P2.row(0);
  A.row(3) = x2.y() * P2.row(2) - P2.row(1);
  for (int r = 0; r < 4; ++r) {
    const double norm = A.row(r).norm();
    if (norm > 0) A.row(r) /= norm;
  }
  Eigen::ColPivHouseholderQR<Eigen::Matrix<double, 4, 3>> qr(A.leftCols<3>());
  qr.setThreshold(1e-10);
  if (qr.rank() < 3) return std::nullopt;  // rays parallel: the point is at infinity
  const Eigen::Vector3d X = qr.solve(-A.col(3));
  if (!X.allFinite()) return std::nullopt;
  return X;
}

bool TriangulationOptions::Check() const {
  return max_reprojection_error_px > 0 && min_parallax_deg >= 0 && min_parallax_deg < 180 && std::isfinite(min_depth);
}

TriangulatedPoint TriangulatePoint(const PinholeCamera& camera, const Eigen::Isometry3d& T_cam1_world,
                                   const Eigen::Isometry3d& T_cam2_world, const Eigen::Vector2d& px1,
                                   const Eigen::Vector2d& px2, const TriangulationOptions& options) {
  FLATSLAM_CHECK(options.Check(), "TriangulatePoint: invalid TriangulationOptions");
  FLATSLAM_CHECK(camera.fx > 0 && camera.fy > 0, "TriangulatePoint: camera has no focal length");
  TriangulatedPoint out;
  const Matrix34d P1 = T_cam1_world.matrix().topRows<3>();
  const Matrix34d P2 = T_cam2_world.matrix().topRows<3>();
  const Eigen::Vector2d x1((px1.x() - camera.cx) / camera.fx, (px1.y() - camera.cy) / camera.fy);
  const Eigen::Vector2d x2((px2.x() - camera.cx) / camera.fx, (px2.y() - camera.cy) / camera.fy);
  const std::optional<Eigen::Vector3d> X = TriangulateDlt(P1, P2, x1, x2);
  if (!X) return out;  // kDegenerate
  out.X_world = *X;
  const Eigen::Vector3d c1 = T_cam1_world.inverse().translation();
  const Eigen::Vector3d c2 = T_cam2_world.inverse().translation();
  out.parallax_deg = ParallaxDeg(*X, c1, c2);
  const Eigen::Vector3d X1 = T_cam1_world * *X;
  const Eigen::Vector3d X2 = T_cam2_world * *X;
  const Eigen::Matrix3d K = camera.K();
  if (X1.z() <= options.min_depth || X2.z() <= options.min_depth) {
    out.status = TriangulationStatus::kBehindCamera;
    return out;
  }
  out.max_error_px = std::sqrt(std::max(ReprojectionError2(K, X1, px1), ReprojectionError2(K, X2, px2)));
  if (!(out.max_error_px <= options.max_reprojection_error_px)) {
    out.status = TriangulationStatus::kLargeError;
    return out;
  }
  if (out.parallax_deg < options.min_parallax_deg) {
    out.status = TriangulationStatus::kLowParallax;
    return out;
  }
  out.status = TriangulationStatus::kOk;
  return out;
}

bool TwoViewOptions::Check() const {
  return ransac_iterations > 0 && local_optimization_passes >= 0 && refine_rounds >= 1 && sigma_px > 0 &&
         chi2_one_dof > 0 && chi2_two_dof > 0 && homography_ratio > 0 && homography_ratio < 1 &&
         max_reprojection_error_px > 0 && min_point_parallax_deg >= 0 && min_parallax_deg >= 0 && parallax_rank >= 0 &&
         min_triangulated >= 0 && min_good_fraction >= 0 && min_good_fraction <= 1 && clear_winner_ratio > 0 &&
         clear_winner_ratio <= 1 && homography_fallback_ratio >= 0 && homography_fallback_ratio <= 1 &&
         refine_iterations >= 1;
}

std::optional<TwoViewResult> InitializeTwoView(const std::vector<Eigen::Vector2d>& px1,
                                               const std::vector<Eigen::Vector2d>& px2, const PinholeCamera& camera,
                                               const TwoViewOptions& options, std::mt19937_64& rng) {
  FLATSLAM_CHECK(px1.size() == px2.size(), "InitializeTwoView: ", px1.size(), " points in view 1 but ", px2.size(),
                 " in view 2");
  FLATSLAM_CHECK(options.Check(), "InitializeTwoView: invalid TwoViewOptions");
  FLATSLAM_CHECK(camera.fx > 0 && camera.fy > 0, "InitializeTwoView: camera has no focal length");
  constexpr int kMinimalSet = 8;
  constexpr int kMinimalHomography = 4;
  const int n = static_cast<int>(px1.size());
  if (n < kMinimalSet) return std::nullopt;

  std::vector<Eigen::Vector2d> x1, x2;
  const Eigen::Matrix3d T1 = Normalize(px1, &x1);
  const Eigen::Matrix3d T2 = Normalize(px2, &x2);
  const Eigen::Matrix3d T2_inv = T2.inverse();
  const double inv_sigma2 = ModelInvSigma2(options);

  auto score_h = [&](const Eigen::Matrix3d& H, ModelScore* out) {
    ScoreHomography(H, px1, px2, inv_sigma2, options.chi2_two_dof, out);
  };
  auto score_f = [&](const Eigen::Matrix3d& F, ModelScore* out) {
    ScoreFundamental(F, px1, px2, inv_sigma2, options.chi2_one_dof, options.chi2_two_dof, out);
  };
  auto fit_h = [&](const int* idx, int count) -> Eigen::Matrix3d {
    return T2_inv * FitHomography(x1, x2, idx, count) * T1;
  };
  // The camera is calibrated: each 8-point F is projected onto the essential manifold (singular
  // values 1, 1, 0 of K^T F K), so hypotheses cannot absorb noise into non-rigid motion.
  const Eigen::Matrix3d K = camera.K();
  const Eigen::Matrix3d K_inv = K.inverse();
  auto fit_f = [&](const int* idx, int count) -> Eigen::Matrix3d {
    const Eigen::Matrix3d F = T2.transpose() * FitFundamental(x1, x2, idx, count) * T1;
    Eigen::JacobiSVD<Eigen::Matrix3d> svd(K.transpose() * F * K, Eigen::ComputeFullU | Eigen::ComputeFullV);
    const Eigen::Matrix3d E = svd.matrixU() * Eigen::Vector3d(1, 1, 0).asDiagonal() * svd.matrixV().transpose();
    return K_inv.transpose() * E * K_inv;
  };
  // Local optimization (LO-RANSAC): re-fit on the consensus set while the score improves.
  ModelScore trial, refit;
  auto local_optimize = [&](auto fit, auto score, Eigen::Matrix3d* model, ModelScore* best) {
    for (int pass = 0; pass < options.local_optimization_passes && best->num_inliers >= kMinimalSet; ++pass) {
      const std::vector<int> inliers = InlierIndices(best->inlier);
      const Eigen::Matrix3d M = fit(inliers.data(), static_cast<int>(inliers.size()));
      score(M, &refit);
      if (!(refit.score > best->score)) break;
      std::swap(*best, refit);
      *model = M;
    }
  };

  // Both hypotheses come from the same minimal sets: F from all 8 points, H from the first 4.
  ModelScore best_h, best_f;
  Eigen::Matrix3d H21 = Eigen::Matrix3d::Identity(), F21 = Eigen::Matrix3d::Zero();
  std::vector<int> pool(n), sample;
  std::iota(pool.begin(), pool.end(), 0);
  for (int it = 0; it < options.ransac_iterations; ++it) {
    SampleIndices(kMinimalSet, &pool, rng, &sample);
    Eigen::Matrix3d H = fit_h(sample.data(), kMinimalHomography);
    score_h(H, &trial);
    if (trial.score > best_h.score) {
      std::swap(best_h, trial);
      H21 = H;
      local_optimize(fit_h, score_h, &H21, &best_h);
    }
    Eigen::Matrix3d F = fit_f(sample.data(), kMinimalSet);
    score_f(F, &trial);
    if (trial.score > best_f.score) {
      std::swap(best_f, trial);
      F21 = F;
      local_optimize(fit_f, score_f, &F21, &best_f);
    }
  }
  const double total = best_h.score + best_f.score;
  if (!(total > 0)) return std::nullopt;
  const double ratio = best_h.score / total;
  const bool prefer_h = ratio > options.homography_ratio;
  auto reconstruct = [&](bool use_h) {
    return use_h ? Reconstruct(MotionsFromHomography(H21, K), best_h, px1, px2, camera, options)
                 : Reconstruct(MotionsFromEssential(K.transpose() * F21 * K), best_f, px1, px2, camera, options);
  };
  // Where neither score dominates (ratio within homography_fallback_ratio of either end) the
  // scores alone do not separate a noisy plane (where F is degenerate) from a 3D scene. With F
  // selected, H is reconstructed too and the better supported wins. With H selected, F is tried
  // only when H gives no answer: a 3D scene seen by a mostly turning camera fits the infinite
  // homography, whose decomposition then stays two-fold ambiguous while F's is clear; on a true
  // plane H answers and the degenerate F is never consulted.
  bool used_h = prefer_h;
  std::optional<Reconstruction> rec = reconstruct(prefer_h);
  const bool undecided = ratio > options.homography_fallback_ratio && ratio < 1.0 - options.homography_fallback_ratio;
  if (options.homography_fallback && undecided && (!prefer_h || !rec)) {
    std::optional<Reconstruction> other = reconstruct(!prefer_h);
    if (other && (!rec || other->good > rec->good)) {
      rec = std::move(other);
      used_h = !prefer_h;
    }
  }
  if (!rec) return std::nullopt;

  std::vector<double> depths;
  for (int i = 0; i < n; ++i)
    if (rec->triangulated[i]) depths.push_back(rec->points[i].z());
  if (static_cast<int>(depths.size()) < std::max(options.min_triangulated, 1)) return std::nullopt;
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
  const double median_depth = depths[depths.size() / 2];
  if (!(median_depth > 0)) return std::nullopt;

  TwoViewResult result;
  const double scale = 1.0 / median_depth;
  result.T_2_1.linear() = rec->motion.R;
  result.T_2_1.translation() = rec->motion.t * scale;
  result.points.assign(n, Eigen::Vector3d::Zero());
  result.triangulated = rec->triangulated;
  for (int i = 0; i < n; ++i) {
    if (!rec->triangulated[i]) continue;
    result.points[i] = rec->points[i] * scale;
    ++result.num_triangulated;
  }
  result.inliers = rec->inliers;
  result.used_homography = used_h;
  result.parallax_deg = rec->parallax_deg;
  result.homography_ratio = ratio;
  return result;
}

StereoDepthRule StereoDepthRule::ForRig(bool stereo, double baseline_m, double far_stereo_baselines,
                                        double far_stereo_level_px) {
  StereoDepthRule rule;
  if (stereo && far_stereo_baselines > 0 && baseline_m > 0) rule.fixed_far_m = far_stereo_baselines * baseline_m;
  if (stereo) rule.min_level_px = std::max(0.0, far_stereo_level_px);
  return rule;
}

std::vector<float>& MeasuredDepths(std::span<const float> depth) {
  thread_local std::vector<float> measured;
  measured.clear();
  for (float d : depth)
    if (d > 0) measured.push_back(d);
  return measured;
}

double StereoDepthRule::FarDepth(std::span<const float> depth) const {
  if (!(fixed_far_m < std::numeric_limits<double>::infinity())) return fixed_far_m;
  std::vector<float>& measured = MeasuredDepths(depth);
  if (measured.empty()) return fixed_far_m;
  std::nth_element(measured.begin(), measured.begin() + measured.size() / 2, measured.end());
  return std::max<double>(fixed_far_m, measured[measured.size() / 2]);
}

Eigen::Isometry3d ScaledMotion(const Eigen::Isometry3d& T, double s) {
  // log: rotation vector w (angle theta) and the twist's translation rho with t = V(w) rho,
  // V(w) = I + (1 - cos theta) / theta^2 [w]x + (theta - sin theta) / theta^3 [w]x^2; exp of
  // s (w, rho) is the rotation by s w and the translation V(s w) s rho.
  const Eigen::AngleAxisd rotation(T.linear());
  const double theta = rotation.angle();
  const auto V = [](const Eigen::Vector3d& w) -> Eigen::Matrix3d {
    const double angle = w.norm();
    Eigen::Matrix3d W;
    W << 0, -w.z(), w.y(), w.z(), 0, -w.x(), -w.y(), w.x(), 0;
    // Series below 1e-4 rad: the closed forms lose their digits to cancellation there.
    const double a = angle < 1e-4 ? 0.5 - angle * angle / 24 : (1 - std::cos(angle)) / (angle * angle);
    const double b = angle < 1e-4 ? 1.0 / 6 - angle * angle / 120 : (angle - std::sin(angle)) / (angle * angle * angle);
    return Eigen::Matrix3d::Identity() + a * W + b * W * W;
  };
  const Eigen::Vector3d w = theta * rotation.axis();
  const Eigen::Vector3d rho = V(w).lu().solve(T.translation());
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  out.linear() = Eigen::AngleAxisd(s * theta, rotation.axis()).toRotationMatrix();
  out.translation() = V(s * w) * (s * rho);
  return out;
}

}  // namespace flatslam
