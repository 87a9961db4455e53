#include "mapping/camera_check.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <unordered_map>
#include <vector>

#include <ceres/ceres.h>
#include <ceres/rotation.h>
#include <Eigen/Geometry>

namespace flatslam {
namespace {

// A left-image keypoint against its keyframe's pose (angle-axis, translation), its point and the
// camera parameters (focal scale, k1); residuals whitened by the keypoint level's sigma.
struct CameraModelResidual {
  double u, v, inv_sigma;
  double fx, fy, cx, cy;

  template <typename T>
  bool operator()(const T* pose, const T* point, const T* model, T* residual) const {
    T Xc[3];
    ceres::AngleAxisRotatePoint(pose, point, Xc);
    for (int i = 0; i < 3; ++i) Xc[i] += pose[3 + i];
    if (Xc[2] <= T(1e-9)) {  // behind the camera: no gradient, a bounded cost
      residual[0] = residual[1] = T(0);
      return true;
    }
    const T x = Xc[0] / Xc[2], y = Xc[1] / Xc[2];
    const T d = T(1) + model[1] * (x * x + y * y);
    residual[0] = (T(cx) + model[0] * T(fx) * x * d - T(u)) * T(inv_sigma);
    residual[1] = (T(cy) + model[0] * T(fy) * y * d - T(v)) * T(inv_sigma);
    return true;
  }
};

// Huber at the 95% chi-square of two degrees of freedom (5.991), on whitened residuals.
constexpr double kHuberDelta = 2.4477;
constexpr size_t kMinPoseObservations = 10;

// Per-coordinate RMS over observations whose whitened squared error is under the chi-square
// gate, in level-0 pixels.
double InlierRmse(const ceres::Problem& problem, const std::vector<ceres::ResidualBlockId>& blocks,
                  const std::vector<double>& sigma) {
  double sum = 0;
  size_t n = 0;
  for (size_t i = 0; i < blocks.size(); ++i) {
    double r[2];
    double cost = 0;
    problem.EvaluateResidualBlock(blocks[i], false, &cost, r, nullptr);
    const double e2 = r[0] * r[0] + r[1] * r[1];
    if (e2 > kHuberDelta * kHuberDelta) continue;
    sum += e2 * sigma[i] * sigma[i];
    n += 2;
  }
  return n == 0 ? 0.0 : std::sqrt(sum / static_cast<double>(n));
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
  std::vector<std::array<double, 6>> poses(order.size());
  for (size_t i = 0; i < order.size(); ++i) {
    const Eigen::Isometry3d& T = map.keyframe(order[i]).T_cam_world;
    const Eigen::AngleAxisd aa(T.linear());
    const Eigen::Vector3d w = aa.angle() * aa.axis();
    poses[i] = {w.x(), w.y(), w.z(), T.translation().x(), T.translation().y(), T.translation().z()};
    slot[order[i].packed()] = i;
  }

  const auto point_values = map.points().values();
  std::vector<std::array<double, 3>> points;
  points.reserve(point_values.size());
  double model[2] = {1.0, 0.0};
  ceres::Problem::Options problem_options;
  problem_options.loss_function_ownership = ceres::DO_NOT_TAKE_OWNERSHIP;
  ceres::Problem problem(problem_options);
  ceres::HuberLoss loss(kHuberDelta);
  std::vector<ceres::ResidualBlockId> blocks;
  std::vector<double> sigmas;
  std::vector<size_t> pose_used(order.size(), 0);  // observations per pose
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
  for (size_t i = 0, rank = 0; i < point_values.size(); ++i) {
    if (!entered[i]) continue;
    if (rank++ % stride != 0) {
      entered[i] = 0;
      continue;
    }
    points.push_back({point_values[i].position.x(), point_values[i].position.y(), point_values[i].position.z()});
  }
  size_t next_point = 0;  // points keeps its size from here on: the addresses stay fixed
  for (size_t i = 0; i < point_values.size(); ++i) {
    if (!entered[i]) continue;
    const MapPoint& p = point_values[i];
    double* X = points[next_point++].data();
    for (const Observation& o : p.observations) {
      const auto it = slot.find(o.keyframe.packed());
      if (it == slot.end()) continue;
      const KeyFrame& kf = map.keyframe(o.keyframe);
      const Eigen::Vector2f uv = kf.uv[o.keypoint];
      const int level = std::min<int>(kf.octave[o.keypoint], std::max(0, geometry.pyramid.levels - 1));
      const double sigma =
          options.pixel_sigma * (geometry.pyramid.levels > 0 ? geometry.pyramid.scale[static_cast<size_t>(level)] : 1.0);
      auto* cost = new ceres::AutoDiffCostFunction<CameraModelResidual, 2, 6, 3, 2>(
          new CameraModelResidual{uv.x(), uv.y(), 1.0 / sigma, cam.fx, cam.fy, cam.cx, cam.cy});
      blocks.push_back(problem.AddResidualBlock(cost, &loss, poses[it->second].data(), X, model));
      sigmas.push_back(sigma);
      ++pose_used[it->second];
    }
  }
  check.observations = blocks.size();
  check.points = points.size();
  if (check.observations < kCameraCheckMinObservations || !pose_used[0] || !pose_used[1]) return check;
  problem.SetParameterBlockConstant(poses[0].data());
  problem.SetParameterBlockConstant(poses[1].data());
  // A keyframe with too few such observations to fix its pose is held where it is.
  for (size_t i = 0; i < order.size(); ++i) {
    if (pose_used[i] > 0) ++check.keyframes;
    if (pose_used[i] > 0 && pose_used[i] < kMinPoseObservations) problem.SetParameterBlockConstant(poses[i].data());
  }
  check.rmse_before_px = InlierRmse(problem, blocks, sigmas);

  ceres::Solver::Options solver_options;
  solver_options.linear_solver_type = ceres::SPARSE_SCHUR;
  solver_options.max_num_iterations = options.max_iterations;
  solver_options.num_threads = 1;
  ceres::Solver::Summary summary;
  ceres::Solve(solver_options, &problem, &summary);
  if (!summary.IsSolutionUsable()) return check;
  check.rmse_after_px = InlierRmse(problem, blocks, sigmas);
  check.focal_scale = model[0];
  check.k1 = model[1];

  // Standard errors of the two camera parameters, the poses and points marginalized: the 2x2
  // block of the inverse of the normal equations, scaled by the residuals' variance per degree of
  // freedom.
  ceres::Covariance::Options covariance_options;
  covariance_options.algorithm_type = ceres::SPARSE_QR;
  covariance_options.num_threads = 1;
  ceres::Covariance covariance(covariance_options);
  const std::vector<std::pair<const double*, const double*>> wanted = {{model, model}};
  if (!covariance.Compute(wanted, &problem)) return check;
  double cov[4];
  if (!covariance.GetCovarianceBlock(model, model, cov)) return check;
  size_t free_parameters = 2 + 3 * points.size();
  for (size_t i = 2; i < order.size(); ++i)
    if (pose_used[i] >= kMinPoseObservations) free_parameters += 6;
  const double dof =
      std::max(1.0, 2.0 * static_cast<double>(check.observations) - static_cast<double>(free_parameters));
  const double variance = 2.0 * summary.final_cost / dof;
  check.focal_scale_sigma = std::sqrt(std::max(0.0, cov[0] * variance));
  check.k1_sigma = std::sqrt(std::max(0.0, cov[3] * variance));
  check.ok = std::isfinite(check.focal_scale) && std::isfinite(check.k1) && std::isfinite(check.focal_scale_sigma) &&
             std::isfinite(check.k1_sigma);
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
