#include "geometry/similarity.h"

#include <algorithm>
#include <cmath>

#include <Eigen/SVD>
#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include "core/error.h"

namespace flatslam {

Eigen::Isometry3d Similarity3::ToIsometry() const {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = t / s;
  return T;
}

std::optional<Similarity3> AlignPoints(std::span<const Eigen::Vector3d> X1, std::span<const Eigen::Vector3d> X2,
                                       bool fix_scale) {
  const size_t n = X1.size();
  if (n < 3 || X2.size() != n) return std::nullopt;
  Eigen::Vector3d m1 = Eigen::Vector3d::Zero(), m2 = Eigen::Vector3d::Zero();
  for (size_t k = 0; k < n; ++k) {
    m1 += X1[k];
    m2 += X2[k];
  }
  m1 /= static_cast<double>(n);
  m2 /= static_cast<double>(n);
  Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
  double var1 = 0;
  for (size_t k = 0; k < n; ++k) {
    const Eigen::Vector3d a = X1[k] - m1, b = X2[k] - m2;
    C += b * a.transpose();
    var1 += a.squaredNorm();
  }
  if (var1 < 1e-12) return std::nullopt;
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(C, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
  if ((svd.matrixU() * svd.matrixV().transpose()).determinant() < 0) D(2, 2) = -1;
  Similarity3 S;
  S.R = svd.matrixU() * D * svd.matrixV().transpose();
  const Eigen::Vector3d sv = svd.singularValues();
  if (sv(1) < 1e-9 * std::max(1.0, sv(0))) return std::nullopt;  // points on a line
  S.s = fix_scale ? 1.0 : (sv(0) * D(0, 0) + sv(1) * D(1, 1) + sv(2) * D(2, 2)) / var1;
  if (!(S.s > 0) || !std::isfinite(S.s)) return std::nullopt;
  S.t = m2 - S.s * S.R * m1;
  return S;
}

namespace {

bool Reprojects(const PinholeCamera& cam, const Eigen::Vector3d& Xc, const Eigen::Vector2d& uv, double gate) {
  if (Xc.z() <= 0) return false;
  const Eigen::Vector2d e = cam.Project(Xc) - uv;
  return e.x() * e.x() + e.y() * e.y() < gate;
}

// Correspondences that reproject both ways under S_21. With to_beat >= 0 the count stops, at
// some value <= to_beat, once the correspondences left cannot take it above to_beat (a RANSAC
// hypothesis that cannot win needs no full count; *inlier is then partial).
int CountInliers(const PinholeCamera& cam, std::span<const PointCorrespondence> m, const Similarity3& S_21, double chi2,
                 std::vector<bool>* inlier, int to_beat = -1) {
  const Similarity3 S_12 = S_21.inverse();
  int n = 0;
  inlier->assign(m.size(), false);
  for (size_t k = 0; k < m.size(); ++k) {
    if (to_beat >= 0 && n + static_cast<int>(m.size() - k) <= to_beat) break;
    const bool ok = Reprojects(cam, S_21 * m[k].X1, m[k].uv2, chi2 * m[k].sigma2_2) &&
                    Reprojects(cam, S_12 * m[k].X2, m[k].uv1, chi2 * m[k].sigma2_1);
    (*inlier)[k] = ok;
    n += ok ? 1 : 0;
  }
  return n;
}

}  // namespace

namespace {

// Reprojection residuals of one correspondence under S_21 (parameters: quaternion of R (Eigen
// order x y z w), t, log s): X1 into camera 2 against uv2 and S_21^-1 X2 into camera 1 against
// uv1, each whitened by its level's sigma.
struct SimilarityReprojectionCost {
  SimilarityReprojectionCost(const PinholeCamera& cam, const PointCorrespondence& m)
      : fx(cam.fx),
        fy(cam.fy),
        cx(cam.cx),
        cy(cam.cy),
        X1(m.X1),
        X2(m.X2),
        uv1(m.uv1),
        uv2(m.uv2),
        w1(1.0 / std::sqrt(m.sigma2_1)),
        w2(1.0 / std::sqrt(m.sigma2_2)) {}

  template <class T>
  bool operator()(const T* q, const T* t, const T* log_s, T* residual) const {
    const T qw[4] = {q[3], q[0], q[1], q[2]};
    const T s = ceres::exp(log_s[0]);
    const T a[3] = {T(X1.x()), T(X1.y()), T(X1.z())};
    T Ra[3];
    ceres::UnitQuaternionRotatePoint(qw, a, Ra);
    const T p2[3] = {s * Ra[0] + t[0], s * Ra[1] + t[1], s * Ra[2] + t[2]};
    // X1' = R^T (X2 - t) / s
    const T q_inv[4] = {q[3], -q[0], -q[1], -q[2]};
    const T b[3] = {T(X2.x()) - t[0], T(X2.y()) - t[1], T(X2.z()) - t[2]};
    T Rb[3];
    ceres::UnitQuaternionRotatePoint(q_inv, b, Rb);
    const T p1[3] = {Rb[0] / s, Rb[1] / s, Rb[2] / s};
    if (p2[2] <= T(1e-6) || p1[2] <= T(1e-6)) {
      for (int k = 0; k < 4; ++k) residual[k] = T(0);
      return true;
    }
    residual[0] = T(w2) * (T(fx) * p2[0] / p2[2] + T(cx) - T(uv2.x()));
    residual[1] = T(w2) * (T(fy) * p2[1] / p2[2] + T(cy) - T(uv2.y()));
    residual[2] = T(w1) * (T(fx) * p1[0] / p1[2] + T(cx) - T(uv1.x()));
    residual[3] = T(w1) * (T(fy) * p1[1] / p1[2] + T(cy) - T(uv1.y()));
    return true;
  }

  double fx, fy, cx, cy;
  Eigen::Vector3d X1, X2;
  Eigen::Vector2d uv1, uv2;
  double w1, w2;
};

// Refines S_21 on the inliers by reprojection error in both images (robust Huber loss).
Similarity3 RefineSimilarity(const PinholeCamera& cam, std::span<const PointCorrespondence> matches,
                             const std::vector<bool>& inlier, const Similarity3& S_21, bool fix_scale, double chi2) {
  Eigen::Quaterniond q(S_21.R);
  q.normalize();
  Eigen::Vector3d t = S_21.t;
  double log_s = std::log(S_21.s);
  ceres::Problem problem;
  for (size_t k = 0; k < matches.size(); ++k) {
    if (!inlier[k]) continue;
    auto* cost = new ceres::AutoDiffCostFunction<SimilarityReprojectionCost, 4, 4, 3, 1>(
        new SimilarityReprojectionCost(cam, matches[k]));
    problem.AddResidualBlock(cost, new ceres::HuberLoss(std::sqrt(chi2)), q.coeffs().data(), t.data(), &log_s);
  }
  if (problem.NumResidualBlocks() == 0) return S_21;
  problem.SetManifold(q.coeffs().data(), new ceres::EigenQuaternionManifold());
  if (fix_scale) problem.SetParameterBlockConstant(&log_s);
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::DENSE_QR;
  solver.max_num_iterations = 10;
  solver.num_threads = 1;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);
  if (!summary.IsSolutionUsable()) return S_21;
  Similarity3 out;
  out.R = q.normalized().toRotationMatrix();
  out.t = t;
  out.s = fix_scale ? 1.0 : std::exp(log_s);
  return out;
}

}  // namespace

std::optional<SimilarityRansacResult> EstimateSimilarityRansac(const PinholeCamera& camera,
                                                               std::span<const PointCorrespondence> matches,
                                                               const SimilarityRansacOptions& options,
                                                               std::mt19937_64& rng) {
  FLATSLAM_CHECK(options.Check(), "invalid similarity RANSAC options");
  const size_t n = matches.size();
  if (n < static_cast<size_t>(options.min_inliers)) return std::nullopt;
  std::uniform_int_distribution<size_t> pick(0, n - 1);
  SimilarityRansacResult best;
  std::vector<bool> inlier;
  for (int it = 0; it < options.iterations; ++it) {
    size_t a = pick(rng), b = pick(rng), c = pick(rng);
    if (a == b || b == c || a == c) continue;
    const Eigen::Vector3d X1[3] = {matches[a].X1, matches[b].X1, matches[c].X1};
    const Eigen::Vector3d X2[3] = {matches[a].X2, matches[b].X2, matches[c].X2};
    const auto S = AlignPoints(X1, X2, options.fix_scale);
    if (!S) continue;
    const int count = CountInliers(camera, matches, *S, options.chi2, &inlier, best.num_inliers);
    if (count > best.num_inliers) {
      best.num_inliers = count;
      best.S_21 = *S;
      best.inlier = inlier;
    }
  }
  if (best.num_inliers < options.min_inliers) return std::nullopt;
  // Refit on the inliers until the set stops growing.
  for (int round = 0; round < 3; ++round) {
    std::vector<Eigen::Vector3d> X1, X2;
    for (size_t k = 0; k < n; ++k) {
      if (!best.inlier[k]) continue;
      X1.push_back(matches[k].X1);
      X2.push_back(matches[k].X2);
    }
    const auto S = AlignPoints(X1, X2, options.fix_scale);
    if (!S) break;
    const int count = CountInliers(camera, matches, *S, options.chi2, &inlier);
    if (count < best.num_inliers) break;
    const bool grew = count > best.num_inliers;
    best = {*S, inlier, count};
    if (!grew) break;
  }
  // The closed form weighs 3D errors, which grow with depth; reprojection errors are what the
  // keypoints measure. Kept when it holds at least as many inliers.
  const Similarity3 refined =
      RefineSimilarity(camera, matches, best.inlier, best.S_21, options.fix_scale, options.chi2);
  const int count = CountInliers(camera, matches, refined, options.chi2, &inlier);
  if (count >= best.num_inliers) best = {refined, inlier, count};
  return best;
}

namespace {

// Residual of edge (i, j): rotation (angle-axis of R_meas^T R_pred), translation and log-scale
// differences between the measured S_ij and S_i * S_j^-1 of the current estimates.
struct EdgeCost {
  EdgeCost(const Similarity3& S_ij, double weight)
      : R_meas_t(S_ij.R.transpose()), t_meas(S_ij.t), log_s_meas(std::log(S_ij.s)), w(std::sqrt(weight)) {}

  template <class T>
  bool operator()(const T* q_i, const T* t_i, const T* ls_i, const T* q_j, const T* t_j, const T* ls_j,
                  T* residual) const {
    // Eigen quaternion storage is (x, y, z, w); ceres rotation helpers take (w, x, y, z).
    const T qi[4] = {q_i[3], q_i[0], q_i[1], q_i[2]};
    const T qj_inv[4] = {q_j[3], -q_j[0], -q_j[1], -q_j[2]};
    T q_ij[4];
    ceres::QuaternionProduct(qi, qj_inv, q_ij);
    T R_pred[9];
    ceres::QuaternionToRotation(q_ij, R_pred);  // row-major
    // R_err = R_meas^T * R_pred
    T R_err[9];
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        R_err[3 * r + c] =
            T(R_meas_t(r, 0)) * R_pred[c] + T(R_meas_t(r, 1)) * R_pred[3 + c] + T(R_meas_t(r, 2)) * R_pred[6 + c];
    // ceres expects column-major for RotationMatrixToAngleAxis; transpose of row-major.
    T R_err_cm[9];
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) R_err_cm[3 * c + r] = R_err[3 * r + c];
    T aa[3];
    ceres::RotationMatrixToAngleAxis(R_err_cm, aa);
    const T s_ij = ceres::exp(ls_i[0] - ls_j[0]);
    T Rt_j[3];
    ceres::UnitQuaternionRotatePoint(q_ij, t_j, Rt_j);
    for (int k = 0; k < 3; ++k) {
      residual[k] = T(w) * aa[k];
      residual[3 + k] = T(w) * (t_i[k] - s_ij * Rt_j[k] - T(t_meas[k]));
    }
    residual[6] = T(w) * (ls_i[0] - ls_j[0] - T(log_s_meas));
    return true;
  }

  Eigen::Matrix3d R_meas_t;
  Eigen::Vector3d t_meas;
  double log_s_meas;
  double w;
};

}  // namespace

double OptimizePoseGraph(std::vector<Similarity3>& S_cw, const std::vector<bool>& fixed,
                         std::span<const PoseGraphEdge> edges, const PoseGraphOptions& options) {
  const size_t n = S_cw.size();
  FLATSLAM_CHECK(fixed.size() == n, "pose graph: ", fixed.size(), " fixed flags for ", n, " nodes");
  std::vector<Eigen::Quaterniond> q(n);
  std::vector<Eigen::Vector3d> t(n);
  std::vector<double> log_s(n);
  for (size_t k = 0; k < n; ++k) {
    q[k] = Eigen::Quaterniond(S_cw[k].R).normalized();
    t[k] = S_cw[k].t;
    log_s[k] = std::log(S_cw[k].s);
  }
  ceres::Problem problem;
  for (const PoseGraphEdge& e : edges) {
    FLATSLAM_CHECK(e.i < n && e.j < n && e.i != e.j, "pose graph edge ", e.i, "-", e.j, " out of range");
    auto* cost = new ceres::AutoDiffCostFunction<EdgeCost, 7, 4, 3, 1, 4, 3, 1>(new EdgeCost(e.S_ij, e.weight));
    problem.AddResidualBlock(cost, nullptr, q[e.i].coeffs().data(), t[e.i].data(), &log_s[e.i], q[e.j].coeffs().data(),
                             t[e.j].data(), &log_s[e.j]);
  }
  for (size_t k = 0; k < n; ++k) {
    if (!problem.HasParameterBlock(q[k].coeffs().data())) continue;
    problem.SetManifold(q[k].coeffs().data(), new ceres::EigenQuaternionManifold());
    if (fixed[k]) {
      problem.SetParameterBlockConstant(q[k].coeffs().data());
      problem.SetParameterBlockConstant(t[k].data());
    }
    if (fixed[k] || options.fix_scale) problem.SetParameterBlockConstant(&log_s[k]);
  }
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.max_num_iterations = options.iterations;
  solver.num_threads = options.num_threads;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);
  for (size_t k = 0; k < n; ++k) {
    S_cw[k].R = q[k].normalized().toRotationMatrix();
    S_cw[k].t = t[k];
    S_cw[k].s = std::exp(log_s[k]);
  }
  return summary.final_cost;
}

}  // namespace flatslam
