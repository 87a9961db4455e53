#include "mapping/rig_check.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include <Eigen/Dense>

namespace flatslam {
namespace {

struct Residual {
  double r = 0;  // measured minus predicted disparity, pixels
  double d = 0;  // predicted disparity
  double w = 0;  // 1 / variance
};

}  // namespace

DisparityOffsetFit FitDisparityOffset(const Map& map, const CameraGeometry& geometry,
                                      const DisparityOffsetOptions& options) {
  DisparityOffsetFit fit;
  if (!(geometry.bf > 0)) return fit;
  const PinholeCamera& cam = geometry.camera;
  const double min_angle = options.min_ray_angle_deg * M_PI / 180.0;
  std::vector<Residual> residuals;
  std::vector<Eigen::Vector3d> rays;
  for (const MapPoint& point : map.points().values()) {
    if (point.observations.size() < options.min_observations) continue;
    // The point from its left-image rays alone: the least-squares meeting point of the rays.
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    rays.clear();
    for (const Observation& o : point.observations) {
      const KeyFrame& kf = map.keyframe(o.keyframe);
      const Eigen::Vector2f uv = kf.uv[o.keypoint];
      const Eigen::Isometry3d T_world_cam = kf.T_cam_world.inverse();
      const Eigen::Vector3d ray =
          (T_world_cam.linear() * Eigen::Vector3d((uv.x() - cam.cx) / cam.fx, (uv.y() - cam.cy) / cam.fy, 1.0))
              .normalized();
      const Eigen::Matrix3d P = Eigen::Matrix3d::Identity() - ray * ray.transpose();
      A += P;
      b += P * T_world_cam.translation();
      rays.push_back(ray);
    }
    double widest = 0;
    for (size_t i = 0; i < rays.size(); ++i)
      for (size_t j = i + 1; j < rays.size(); ++j)
        widest = std::max(widest, std::acos(std::clamp(rays[i].dot(rays[j]), -1.0, 1.0)));
    if (widest < min_angle) continue;
    const Eigen::Vector3d X = A.ldlt().solve(b);
    bool used = false;
    for (const Observation& o : point.observations) {
      const KeyFrame& kf = map.keyframe(o.keyframe);
      const float right_u = kf.right_u[o.keypoint];
      if (right_u < 0) continue;
      const Eigen::Vector3d Xc = kf.T_cam_world * X;
      if (Xc.z() <= 0) continue;
      const double predicted = geometry.bf / Xc.z();
      const double measured = kf.uv[o.keypoint].x() - right_u;
      const double scale =
          geometry.pyramid.scale[std::min<size_t>(kf.octave[o.keypoint], geometry.pyramid.scale.size() - 1)];
      // Noise of the measurement, and of the prediction: a ray's pixel error over the rays' angle is
      // the relative depth error of the point they place.
      const double sigma_measured = options.pixel_sigma * scale;
      const double sigma_predicted = predicted * (scale / cam.fx) / widest;
      residuals.push_back({measured - predicted, predicted,
                           1.0 / (sigma_measured * sigma_measured + sigma_predicted * sigma_predicted)});
      used = true;
    }
    fit.points += used;
  }
  if (residuals.size() < 100) return fit;

  // Weighted least squares of r = offset + slope * d, dropping residuals beyond 3 sigma each round.
  std::vector<bool> kept(residuals.size(), true);
  for (int iteration = 0; iteration < std::max(1, options.trim_iterations); ++iteration) {
    Eigen::Matrix2d N = Eigen::Matrix2d::Zero();
    Eigen::Vector2d g = Eigen::Vector2d::Zero();
    size_t n = 0;
    for (size_t i = 0; i < residuals.size(); ++i) {
      if (!kept[i]) continue;
      const Eigen::Vector2d a(1.0, residuals[i].d);
      N += residuals[i].w * a * a.transpose();
      g += residuals[i].w * a * residuals[i].r;
      ++n;
    }
    if (n < 100 || std::abs(N.determinant()) < 1e-12) return fit;
    const Eigen::Vector2d x = N.ldlt().solve(g);
    double chi2 = 0;
    for (size_t i = 0; i < residuals.size(); ++i) {
      if (!kept[i]) continue;
      const double e = residuals[i].r - x[0] - x[1] * residuals[i].d;
      chi2 += residuals[i].w * e * e;
    }
    const double variance = chi2 / static_cast<double>(n - 2);
    fit.ok = true;
    fit.offset_px = x[0];
    fit.slope = x[1];
    const Eigen::Matrix2d covariance = N.inverse();
    fit.offset_sigma_px = std::sqrt(covariance(0, 0) * variance);
    fit.observations = n;
    for (size_t i = 0; i < residuals.size(); ++i) {
      const double e = residuals[i].r - x[0] - x[1] * residuals[i].d;
      kept[i] = residuals[i].w * e * e < 9 * variance;
    }
  }
  std::vector<double> disparities;
  for (size_t i = 0; i < residuals.size(); ++i)
    if (kept[i]) disparities.push_back(residuals[i].d);
  if (!disparities.empty()) {
    std::nth_element(disparities.begin(), disparities.begin() + disparities.size() / 2, disparities.end());
    fit.median_disparity_px = disparities[disparities.size() / 2];
  }
  return fit;
}

std::string DescribeDisparityOffset(const DisparityOffsetFit& fit, double offset_set_px) {
  if (!fit.ok) return {};
  char line[320];
  int n = std::snprintf(line, sizeof(line),
                        "disparities %+.3f +- %.3f px off the map's multi-view points (%zu observations of %zu "
                        "points, median disparity %.1f px)",
                        fit.offset_px, fit.offset_sigma_px, fit.observations, fit.points, fit.median_disparity_px);
  std::string out(line, static_cast<size_t>(std::max(0, n)));
  const double size = std::abs(fit.offset_px);
  if (size > std::max(0.05, 3 * fit.offset_sigma_px) && size >= 0.005 * fit.median_disparity_px) {
    n = std::isnan(offset_set_px)
            ? std::snprintf(line, sizeof(line),
                            "; if the rig's rectification is off by that, adding %.2f to the run's "
                            "stereo.disparity_offset_px takes it off",
                            fit.offset_px)
            : std::snprintf(line, sizeof(line),
                            "; if the rig's rectification is off by that, --set stereo.disparity_offset_px=%.2f takes "
                            "it off",
                            offset_set_px + fit.offset_px);
    out.append(line, static_cast<size_t>(std::max(0, n)));
  }
  return out;
}

}  // namespace flatslam
