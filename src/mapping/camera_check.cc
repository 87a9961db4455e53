#include "mapping/camera_check.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <unordered_map>
#include <vector>

#include <Eigen/Cholesky>
#include <Eigen/Geometry>

#include "optimization/lm_terms.h"

namespace flatslam {
namespace {

// Huber at the 95% chi-square of two degrees of freedom (5.991), on whitened residuals.
constexpr double kHuberDelta = 2.4477;
constexpr size_t kMinPoseObservations = 10;
// The poses adjusted at most: the reduced system is dense in the free poses (6 each) and the two
// camera parameters, and a 722-wide Cholesky factorization per iteration stays within a few tens
// of milliseconds; beyond it the keyframes seen by the fewest entered points are held.
constexpr size_t kMaxFreePoses = 120;

// A left-image keypoint of a keyframe pose and an entered point, whitened by its level's sigma.
struct CheckObservation {
  uint32_t pose, point;
  double u, v, sigma;
};

struct CheckPose {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
};

// The model's state: every pose, point and the two camera parameters (focal scale, k1).
struct CheckState {
  std::vector<CheckPose> poses;
  std::vector<Eigen::Vector3d> points;
  Eigen::Vector2d model{1.0, 0.0};
};

// One observation's whitened residual through the state, and its Jacobians with respect to the
// pose (a rotation and a translation applied on the left: R <- exp(w) R, t <- exp(w) t + dt), the
// point and the model. False behind the camera: no residual and no gradient (a bounded cost).
struct ObservationTerm {
  Eigen::Vector2d r;
  Eigen::Matrix<double, 2, 6> Jc;
  Eigen::Matrix<double, 2, 3> Jp;
  Eigen::Matrix2d Jm;
};

bool Linearize(const CheckState& state, const CheckObservation& o, const PinholeCamera& cam, bool jacobians,
               ObservationTerm* term) {
  const CheckPose& pose = state.poses[o.pose];
  const Eigen::Vector3d Xc = pose.R * state.points[o.point] + pose.t;
  if (Xc.z() <= 1e-9) return false;
  const double iz = 1.0 / Xc.z(), x = Xc.x() * iz, y = Xc.y() * iz, r2 = x * x + y * y;
  const double s = state.model[0], k1 = state.model[1], d = 1 + k1 * r2, w = 1.0 / o.sigma;
  term->r = Eigen::Vector2d((cam.cx + s * cam.fx * x * d - o.u) * w, (cam.cy + s * cam.fy * y * d - o.v) * w);
  if (!jacobians) return true;
  // d(residual)/d(x, y), then d(x, y)/d(Xc).
  Eigen::Matrix2d Juv;
  Juv << s * cam.fx * (d + 2 * k1 * x * x), s * cam.fx * 2 * k1 * x * y, s * cam.fy * 2 * k1 * x * y,
      s * cam.fy * (d + 2 * k1 * y * y);
  Eigen::Matrix<double, 2, 3> Jxy;
  Jxy << iz, 0, -x * iz, 0, iz, -y * iz;
  const Eigen::Matrix<double, 2, 3> JX = w * Juv * Jxy;
  term->Jc.leftCols<3>() = -JX * detail::Skew(Xc);
  term->Jc.rightCols<3>() = JX;
  term->Jp = JX * pose.R;
  term->Jm << w * cam.fx * x * d, w * s * cam.fx * x * r2, w * cam.fy * y * d, w * s * cam.fy * y * r2;
  return true;
}

// Huber's rho and weight on a squared whitened residual.
double HuberRho(double e2) {
  double rho = 0, weight = 0;
  detail::Huber(e2, kHuberDelta, true, &rho, &weight);
  return rho;
}
double HuberWeight(double e2) {
  double rho = 0, weight = 0;
  detail::Huber(e2, kHuberDelta, true, &rho, &weight);
  return weight;
}

double Cost(const CheckState& state, const std::vector<CheckObservation>& obs, const PinholeCamera& cam) {
  double cost = 0;
  ObservationTerm term;
  for (const CheckObservation& o : obs)
    if (Linearize(state, o, cam, false, &term)) cost += 0.5 * HuberRho(term.r.squaredNorm());
  return cost;
}

// Per-coordinate RMS over observations whose whitened squared error is under the chi-square
// gate, in level-0 pixels.
double InlierRmse(const CheckState& state, const std::vector<CheckObservation>& obs, const PinholeCamera& cam) {
  double sum = 0;
  size_t n = 0;
  ObservationTerm term;
  for (const CheckObservation& o : obs) {
    if (!Linearize(state, o, cam, false, &term)) {
      n += 2;  // behind the camera: a zero residual, as the adjustment sees it
      continue;
    }
    const double e2 = term.r.squaredNorm();
    if (e2 > kHuberDelta * kHuberDelta) continue;
    sum += e2 * o.sigma * o.sigma;
    n += 2;
  }
  return n == 0 ? 0.0 : std::sqrt(sum / static_cast<double>(n));
}

// The normal equations at a state, undamped: the camera side (free poses and the model) H and g,
// the points' 3x3 blocks V and gradients, and each observation's coupling W.
struct Linearization {
  Eigen::MatrixXd H;
  Eigen::VectorXd g;
  std::vector<Eigen::Matrix3d> V;              // per point, Jp^T W Jp
  std::vector<Eigen::Vector3d> g_point;        // per point, J^T W r
  std::vector<Eigen::Matrix<double, 3, 8>> W;  // per observation, Jp^T W [Jc Jm] (pose columns zero when held)
};

// free_slot[pose] is the pose's block in the camera side, or -1 when held.
Linearization LinearizeAll(const CheckState& state, const std::vector<CheckObservation>& obs,
                           const std::vector<int>& free_slot, size_t free_poses, const PinholeCamera& cam) {
  Linearization lin;
  const Eigen::Index n = static_cast<Eigen::Index>(6 * free_poses + 2), m = n - 2;
  lin.H = Eigen::MatrixXd::Zero(n, n);
  lin.g = Eigen::VectorXd::Zero(n);
  lin.V.assign(state.points.size(), Eigen::Matrix3d::Zero());
  lin.g_point.assign(state.points.size(), Eigen::Vector3d::Zero());
  lin.W.assign(obs.size(), Eigen::Matrix<double, 3, 8>::Zero());
  ObservationTerm term;
  for (size_t i = 0; i < obs.size(); ++i) {
    const CheckObservation& o = obs[i];
    if (!Linearize(state, o, cam, true, &term)) continue;
    const double w = HuberWeight(term.r.squaredNorm());
    Eigen::Matrix<double, 2, 8> Jcm;
    const int slot = free_slot[o.pose];
    Jcm.leftCols<6>() = slot >= 0 ? term.Jc : Eigen::Matrix<double, 2, 6>::Zero();
    Jcm.rightCols<2>() = term.Jm;
    const Eigen::Matrix<double, 8, 8> Hcc = w * Jcm.transpose() * Jcm;
    const Eigen::Matrix<double, 8, 1> gc = w * Jcm.transpose() * term.r;
    if (slot >= 0) {
      lin.H.block<6, 6>(6 * slot, 6 * slot) += Hcc.topLeftCorner<6, 6>();
      lin.H.block<6, 2>(6 * slot, m) += Hcc.topRightCorner<6, 2>();
      lin.H.block<2, 6>(m, 6 * slot) += Hcc.bottomLeftCorner<2, 6>();
      lin.g.segment<6>(6 * slot) += gc.head<6>();
    }
    lin.H.block<2, 2>(m, m) += Hcc.bottomRightCorner<2, 2>();
    lin.g.tail<2>() += gc.tail<2>();
    lin.V[o.point] += w * term.Jp.transpose() * term.Jp;
    lin.g_point[o.point] += w * term.Jp.transpose() * term.r;
    lin.W[i] = w * term.Jp.transpose() * Jcm;
  }
  return lin;
}

// The normal equations reduced to the free poses and the model (the points eliminated), damped
// by lambda on their diagonals: S dc = rhs, and each point's (V + damping)^-1 for back-substitution.
struct ReducedSystem {
  Eigen::MatrixXd S;
  Eigen::VectorXd rhs;
  std::vector<Eigen::Matrix3d> V_inv;
};

// Observations are grouped by point.
ReducedSystem Eliminate(const Linearization& lin, const std::vector<CheckObservation>& obs,
                        const std::vector<int>& free_slot, double lambda) {
  ReducedSystem sys;
  Eigen::MatrixXd H = lin.H;
  Eigen::VectorXd g = lin.g;
  const Eigen::Index n = H.rows(), m = n - 2;
  sys.V_inv.assign(lin.V.size(), Eigen::Matrix3d::Zero());
  for (Eigen::Index k = 0; k < n; ++k) H(k, k) += lambda * std::max(H(k, k), 1e-6);
  // Eliminate each point: S = Hcc - sum Wp^T V^-1 Wp over the point's observations.
  for (size_t begin = 0; begin < obs.size();) {
    const uint32_t p = obs[begin].point;
    size_t end = begin;
    while (end < obs.size() && obs[end].point == p) ++end;
    Eigen::Matrix3d Vp = lin.V[p];
    for (int k = 0; k < 3; ++k) Vp(k, k) += lambda * std::max(Vp(k, k), 1e-6);
    if (std::abs(Vp.determinant()) < 1e-18) {
      begin = end;
      continue;
    }
    const Eigen::Matrix3d Vi = Vp.inverse();
    sys.V_inv[p] = Vi;
    // The model's columns are shared by every observation of the point: summed first.
    Eigen::Matrix<double, 3, 2> Wm = Eigen::Matrix<double, 3, 2>::Zero();
    for (size_t a = begin; a < end; ++a) Wm += lin.W[a].rightCols<2>();
    const Eigen::Vector3d Vg = Vi * lin.g_point[p];
    const Eigen::Matrix<double, 3, 2> ViWm = Vi * Wm;
    for (size_t a = begin; a < end; ++a) {
      const int sa = free_slot[obs[a].pose];
      if (sa < 0) continue;
      const Eigen::Matrix<double, 3, 6> Wa = lin.W[a].leftCols<6>();
      const Eigen::Matrix<double, 6, 3> WaVi = Wa.transpose() * Vi;
      // Only the lower triangle: the Cholesky and LDLT factorizations read nothing else.
      for (size_t b = begin; b < end; ++b) {
        const int sb = free_slot[obs[b].pose];
        if (sb >= 0 && sb <= sa) H.block<6, 6>(6 * sa, 6 * sb) -= WaVi * lin.W[b].leftCols<6>();
      }
      H.block<2, 6>(m, 6 * sa) -= ViWm.transpose() * Wa;
      g.segment<6>(6 * sa) -= Wa.transpose() * Vg;
    }
    H.block<2, 2>(m, m) -= Wm.transpose() * ViWm;
    g.tail<2>() -= Wm.transpose() * Vg;
    begin = end;
  }
  sys.S = std::move(H);  // its upper triangle is not reduced: read it through a lower view only
  sys.rhs = -g;
  return sys;
}

// The state after the step dc of the reduced system, the points' steps back-substituted.
CheckState Step(const CheckState& state, const Linearization& lin, const ReducedSystem& sys, const Eigen::VectorXd& dc,
                const std::vector<CheckObservation>& obs, const std::vector<int>& free_slot) {
  CheckState next = state;
  for (size_t i = 0; i < state.poses.size(); ++i) {
    if (free_slot[i] < 0) continue;
    const Eigen::Matrix<double, 6, 1> xi = dc.segment<6>(6 * free_slot[i]);
    const Eigen::Matrix3d dR = detail::ExpSo3(xi.head<3>());
    next.poses[i].R = dR * state.poses[i].R;
    next.poses[i].t = dR * state.poses[i].t + xi.tail<3>();
  }
  next.model += dc.tail<2>();
  // dp = V^-1 (-g_p - sum W dc) over the point's observations (each W holds the model's columns
  // of its observation; their sum over the point is what the elimination used).
  std::vector<Eigen::Vector3d> coupling(state.points.size(), Eigen::Vector3d::Zero());
  Eigen::Matrix<double, 8, 1> d8;
  d8.tail<2>() = dc.tail<2>();
  for (size_t i = 0; i < obs.size(); ++i) {
    const int slot = free_slot[obs[i].pose];
    d8.head<6>() = slot >= 0 ? Eigen::Matrix<double, 6, 1>(dc.segment<6>(6 * slot)) : Eigen::Matrix<double, 6, 1>::Zero();
    coupling[obs[i].point] += lin.W[i] * d8;
  }
  for (size_t p = 0; p < state.points.size(); ++p)
    next.points[p] += sys.V_inv[p] * (-lin.g_point[p] - coupling[p]);
  return next;
}

}  // namespace

CameraCheck CheckCameraModel(const Map& map, const CameraGeometry& geometry, const CameraCheckOptions& options) {
  CameraCheck check;
  const PinholeCamera& cam = geometry.camera;
  if (!cam.valid()) return check;

  // Keyframes in id order; the two oldest hold the gauge.
  std::vector<KeyFrameHandle> order(map.keyframes().handles().begin(), map.keyframes().handles().end());
  std::sort(order.begin(), order.end(),
            [&](KeyFrameHandle a, KeyFrameHandle b) { return map.keyframe(a).id < map.keyframe(b).id; });
  if (order.size() < 3) return check;
  std::unordered_map<uint64_t, size_t> slot;  // handle bits -> pose index
  CheckState state;
  state.poses.resize(order.size());
  for (size_t i = 0; i < order.size(); ++i) {
    const Eigen::Isometry3d& T = map.keyframe(order[i]).T_cam_world;
    state.poses[i] = {T.linear(), T.translation()};
    slot[order[i].packed()] = i;
  }

  const auto point_values = map.points().values();
  // A point enters when its left-image rays fix its depth: seen by enough keyframes, rays at
  // least min_ray_angle_deg apart (a stereo or RGB-D map holds points placed from one keyframe's
  // depth and seen again from nearby, whose depth the left images alone leave open).
  const double min_cos = std::cos(options.min_ray_angle_deg * M_PI / 180.0);
  std::vector<Eigen::Vector3d> rays;
  auto enters = [&](const MapPoint& p) {
    if (p.observations.size() < std::max<size_t>(options.min_observations, 2)) return false;
    rays.clear();
    for (const Observation& o : p.observations) {
      if (!slot.count(o.keyframe.packed())) continue;
      rays.push_back((p.position - map.keyframe(o.keyframe).camera_center()).normalized());
    }
    for (size_t i = 0; i < rays.size(); ++i)
      for (size_t j = i + 1; j < rays.size(); ++j)
        if (rays[i].dot(rays[j]) <= min_cos) return true;
    return false;
  };
  std::vector<uint8_t> entered(point_values.size(), 0);
  size_t qualified = 0;
  for (size_t i = 0; i < point_values.size(); ++i) qualified += entered[i] = enters(point_values[i]) ? 1 : 0;
  const size_t stride =
      options.max_points > 0 && qualified > options.max_points ? (qualified + options.max_points - 1) / options.max_points : 1;
  std::vector<CheckObservation> obs;
  std::vector<size_t> pose_used(order.size(), 0);  // observations per pose
  for (size_t i = 0, rank = 0; i < point_values.size(); ++i) {
    if (!entered[i] || rank++ % stride != 0) continue;
    const MapPoint& p = point_values[i];
    const auto point = static_cast<uint32_t>(state.points.size());
    state.points.push_back(p.position);
    for (const Observation& o : p.observations) {
      const auto it = slot.find(o.keyframe.packed());
      if (it == slot.end()) continue;
      const KeyFrame& kf = map.keyframe(o.keyframe);
      const Eigen::Vector2f uv = kf.uv[o.keypoint];
      const int level = std::min<int>(kf.octave[o.keypoint], std::max(0, geometry.pyramid.levels - 1));
      const double sigma =
          options.pixel_sigma * (geometry.pyramid.levels > 0 ? geometry.pyramid.scale[static_cast<size_t>(level)] : 1.0);
      obs.push_back({static_cast<uint32_t>(it->second), point, uv.x(), uv.y(), sigma});
      ++pose_used[it->second];
    }
  }
  check.observations = obs.size();
  check.points = state.points.size();
  if (check.observations < kCameraCheckMinObservations || !pose_used[0] || !pose_used[1]) return check;
  // Free: every pose but the gauge's two with kMinPoseObservations or more (a keyframe with fewer
  // is held where it is), at most kMaxFreePoses of them, those with the most observations.
  std::vector<size_t> candidates;
  for (size_t i = 0; i < order.size(); ++i) {
    if (pose_used[i] > 0) ++check.keyframes;
    if (i >= 2 && pose_used[i] >= kMinPoseObservations) candidates.push_back(i);
  }
  if (candidates.size() > kMaxFreePoses) {
    std::stable_sort(candidates.begin(), candidates.end(), [&](size_t a, size_t b) { return pose_used[a] > pose_used[b]; });
    candidates.resize(kMaxFreePoses);
    std::sort(candidates.begin(), candidates.end());
  }
  std::vector<int> free_slot(order.size(), -1);
  for (size_t k = 0; k < candidates.size(); ++k) free_slot[candidates[k]] = static_cast<int>(k);
  const size_t free_poses = candidates.size();
  check.rmse_before_px = InlierRmse(state, obs, cam);

  // Levenberg-Marquardt on the robust cost (Huber weights per iteration), to a relative decrease
  // of 1e-6 of the cost on an accepted step; the damping falls by 3 after an accepted step and
  // grows by 4 after a rejected one.
  // A rejected step only changes the damping: the linearization is kept until a step is accepted,
  // and the one at the solution gives the standard errors below.
  double cost = Cost(state, obs, cam), lambda = 1e-4;
  Linearization lin = LinearizeAll(state, obs, free_slot, free_poses, cam);
  for (int it = 0; it < options.max_iterations && lambda < 1e12; ++it) {
    const ReducedSystem sys = Eliminate(lin, obs, free_slot, lambda);
    const Eigen::LLT<Eigen::MatrixXd> llt(sys.S);
    if (llt.info() != Eigen::Success) {
      lambda *= 10;
      continue;
    }
    CheckState next = Step(state, lin, sys, llt.solve(sys.rhs), obs, free_slot);
    const double next_cost = Cost(next, obs, cam);
    if (!std::isfinite(next_cost) || next_cost >= cost) {
      lambda *= 4;
      continue;
    }
    const double decrease = (cost - next_cost) / cost;
    state = std::move(next);
    cost = next_cost;
    lin = LinearizeAll(state, obs, free_slot, free_poses, cam);
    lambda = std::max(lambda / 3, 1e-12);
    if (decrease < 1e-6) break;
  }
  check.rmse_after_px = InlierRmse(state, obs, cam);
  check.focal_scale = state.model[0];
  check.k1 = state.model[1];

  // Standard errors of the two camera parameters, the poses and points marginalized: the 2x2
  // block of the inverse of the normal equations, scaled by the residuals' variance per degree of
  // freedom.
  const ReducedSystem sys = Eliminate(lin, obs, free_slot, 0);
  const Eigen::LDLT<Eigen::MatrixXd> ldlt(sys.S);
  if (ldlt.info() != Eigen::Success) return check;
  const Eigen::Index n = sys.S.rows();
  Eigen::MatrixXd unit = Eigen::MatrixXd::Zero(n, 2);
  unit(n - 2, 0) = unit(n - 1, 1) = 1;
  const Eigen::MatrixXd inverse = ldlt.solve(unit);
  const double cov_focal = inverse(n - 2, 0), cov_k1 = inverse(n - 1, 1);
  const size_t free_parameters = 2 + 3 * state.points.size() + 6 * free_poses;
  const double dof =
      std::max(1.0, 2.0 * static_cast<double>(check.observations) - static_cast<double>(free_parameters));
  const double variance = 2.0 * cost / dof;
  check.focal_scale_sigma = std::sqrt(std::max(0.0, cov_focal * variance));
  check.k1_sigma = std::sqrt(std::max(0.0, cov_k1 * variance));
  check.ok = std::isfinite(check.focal_scale) && std::isfinite(check.k1) && std::isfinite(check.focal_scale_sigma) &&
             std::isfinite(check.k1_sigma) && cov_focal > 0 && cov_k1 > 0;
  return check;
}

namespace {

double Sigmas(double delta, double sigma) { return sigma > 0 ? std::abs(delta) / sigma : INFINITY; }

}  // namespace

bool CameraCheckDisagrees(const CameraCheck& check) {
  return check.ok && (Sigmas(check.focal_scale - 1, check.focal_scale_sigma) > kCameraCheckDisagreeSigmas ||
                      Sigmas(check.k1, check.k1_sigma) > kCameraCheckDisagreeSigmas);
}

double CameraCheckCornerShiftPx(const CameraCheck& check, const PinholeCamera& camera) {
  // The corner farthest from the principal point, in the given model's normalized coordinates.
  const double x = std::max(camera.cx, camera.width - camera.cx) / camera.fx;
  const double y = std::max(camera.cy, camera.height - camera.cy) / camera.fy;
  const double d = check.focal_scale * (1 + check.k1 * (x * x + y * y)) - 1;
  return std::hypot(camera.fx * x * d, camera.fy * y * d);
}

std::string DescribeCameraCheck(const CameraCheck& check, const PinholeCamera& camera) {
  if (!check.ok) return {};
  const double focal_sigmas = Sigmas(check.focal_scale - 1, check.focal_scale_sigma);
  const double k1_sigmas = Sigmas(check.k1, check.k1_sigma);
  char text[640];
  std::snprintf(text, sizeof text,
                "fx %.2f +- %.2f (given %.2f: %+.2f%%, %.1f sigma), k1 %+.4f +- %.4f (given 0: %.1f sigma); "
                "reprojection %.3f -> %.3f px over %zu observations of %zu points in %zu keyframes",
                camera.fx * check.focal_scale, camera.fx * check.focal_scale_sigma, camera.fx,
                100 * (check.focal_scale - 1), focal_sigmas, check.k1, check.k1_sigma, k1_sigmas, check.rmse_before_px,
                check.rmse_after_px, check.observations, check.points, check.keyframes);
  std::string out = text;
  if (CameraCheckDisagrees(check))
    out += "\n  the map's keypoints disagree with the camera model: a monocular map's scale follows such an error "
           "through turns; try the refined camera (--settings) and compare";
  else
    out += "\n  the map's keypoints agree with the camera model, within what its motion can tell";
  return out;
}

}  // namespace flatslam
