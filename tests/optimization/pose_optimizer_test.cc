#include "optimization/pose_optimizer.h"

#include <chrono>
#include <cmath>
#include <random>

#include <ceres/manifold.h>
#include <gtest/gtest.h>

#include "core/error.h"
#include "geometry/geometry_fixtures.h"

namespace flatslam {
namespace {

using testing::kDeg;
using testing::kPi;
using testing::Pose;
using testing::RandomUnit;
using testing::TestCamera;

// Moves T by exactly `meters` and `degrees` in random directions.
Eigen::Isometry3d Perturb(const Eigen::Isometry3d& T, double meters, double degrees, std::mt19937_64& rng) {
  Eigen::Isometry3d out = T;
  out.linear() = Eigen::AngleAxisd(degrees * kDeg, RandomUnit(rng)).toRotationMatrix() * T.linear();
  out.translation() = T.translation() + meters * RandomUnit(rng);
  return out;
}

struct PoseScene {
  PinholeCamera camera = TestCamera();
  double baseline_m = 0.12;
  Eigen::Isometry3d T_cam_world_true;
  std::vector<PoseObservation> observations;
  std::vector<bool> is_outlier;
};

// n observations of points 1.5..15 m in front of the camera; 1 px noise (scaled by octave);
// a fraction displaced by 15..80 px. Stereo observations for points closer than 40 baselines.
PoseScene MakePoseScene(int n, double outlier_fraction, bool stereo, uint64_t seed) {
  PoseScene s;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0, 1);
  std::normal_distribution<double> noise(0, 1);
  const double scale_factor = 1.2;
  s.T_cam_world_true = Pose(Eigen::AngleAxisd(0.7, Eigen::Vector3d(0.2, 1, -0.1).normalized()).toRotationMatrix(),
                            Eigen::Vector3d(1.0, -0.5, 2.0));
  const Eigen::Isometry3d T_world_cam = s.T_cam_world_true.inverse();
  const double bf = s.camera.fx * s.baseline_m;
  while (static_cast<int>(s.observations.size()) < n) {
    const Eigen::Vector2d px(unit(rng) * s.camera.width, unit(rng) * s.camera.height);
    const double z = 1.5 + 13.5 * unit(rng);
    const Eigen::Vector3d x_cam((px.x() - s.camera.cx) / s.camera.fx * z, (px.y() - s.camera.cy) / s.camera.fy * z, z);
    PoseObservation obs;
    obs.X_world = T_world_cam * x_cam;
    const int octave = static_cast<int>(unit(rng) * 4);
    const double sigma = std::pow(scale_factor, octave);
    obs.inv_sigma2 = static_cast<float>(1.0 / (sigma * sigma));
    obs.uv = px + sigma * Eigen::Vector2d(noise(rng), noise(rng));
    if (stereo && z < 40 * s.baseline_m) obs.right_u = px.x() - bf / z + sigma * noise(rng);
    const bool outlier = unit(rng) < outlier_fraction;
    if (outlier) {
      const double angle = 2 * kPi * unit(rng);
      obs.uv += (15 + 65 * unit(rng)) * Eigen::Vector2d(std::cos(angle), std::sin(angle));
      if (obs.right_u >= 0) obs.right_u = std::max(0.0, obs.uv.x() - 30 * unit(rng));
    }
    s.observations.push_back(obs);
    s.is_outlier.push_back(outlier);
  }
  return s;
}

void CheckConverges(bool stereo) {
  const PoseScene scene = MakePoseScene(200, 0.3, stereo, stereo ? 21 : 20);
  std::mt19937_64 rng(5);
  const Eigen::Isometry3d T_init = Perturb(scene.T_cam_world_true, 0.10, 5.0, rng);
  const PoseOptimizationResult r =
      OptimizePose(scene.camera, scene.baseline_m, T_init, scene.observations, PoseOptimizerOptions{});
  ASSERT_TRUE(r.success);
  // Compare camera centres and orientations.
  const Eigen::Isometry3d T_err = r.T_cam_world * scene.T_cam_world_true.inverse();
  const double rot_err = Eigen::AngleAxisd(T_err.linear()).angle() / kDeg;
  const double pos_err =
      (r.T_cam_world.inverse().translation() - scene.T_cam_world_true.inverse().translation()).norm();
  int correct = 0, outliers_flagged = 0, outliers = 0;
  for (size_t i = 0; i < scene.observations.size(); ++i) {
    correct += r.inlier[i] != scene.is_outlier[i];
    outliers += scene.is_outlier[i];
    outliers_flagged += scene.is_outlier[i] && !r.inlier[i];
  }
  const double correct_fraction = static_cast<double>(correct) / scene.observations.size();
  printf(
      "  %s: position error %.2f mm, rotation error %.4f deg, inliers %d/%zu, classified %.1f%% correctly, "
      "outliers flagged %d/%d\n",
      stereo ? "stereo" : "mono", pos_err * 1e3, rot_err, r.num_inliers, scene.observations.size(),
      100 * correct_fraction, outliers_flagged, outliers);
  EXPECT_LT(pos_err, 0.01);
  EXPECT_LT(rot_err, 0.1);
  EXPECT_GT(correct_fraction, 0.95);
  EXPECT_EQ(outliers_flagged, outliers);
  int inlier_count = 0;
  for (bool b : r.inlier) inlier_count += b;
  EXPECT_EQ(inlier_count, r.num_inliers);

  // Time the call (not asserted: shared machines).
  constexpr int kRuns = 200;
  const auto start = std::chrono::steady_clock::now();
  for (int k = 0; k < kRuns; ++k) {
    const PoseOptimizationResult again =
        OptimizePose(scene.camera, scene.baseline_m, T_init, scene.observations, PoseOptimizerOptions{});
    ASSERT_TRUE(again.T_cam_world.matrix() == r.T_cam_world.matrix());  // deterministic
  }
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count() / kRuns;
  printf("  %s: OptimizePose on %zu observations: %.3f ms per call\n", stereo ? "stereo" : "mono",
         scene.observations.size(), ms);
}

TEST(OptimizePose, MonoConvergesAndFlagsOutliers) {
  CheckConverges(false);
}

TEST(OptimizePose, StereoConvergesAndFlagsOutliers) {
  CheckConverges(true);
}

TEST(OptimizePose, NoiseFreeIsExact) {
  PoseScene scene = MakePoseScene(60, 0.0, true, 3);
  // Re-project without noise.
  const double bf = scene.camera.fx * scene.baseline_m;
  for (PoseObservation& obs : scene.observations) {
    const Eigen::Vector3d x = scene.T_cam_world_true * obs.X_world;
    obs.uv = Eigen::Vector2d(scene.camera.fx * x.x() / x.z() + scene.camera.cx,
                             scene.camera.fy * x.y() / x.z() + scene.camera.cy);
    if (obs.right_u >= 0) obs.right_u = obs.uv.x() - bf / x.z();
  }
  std::mt19937_64 rng(2);
  const PoseOptimizationResult r =
      OptimizePose(scene.camera, scene.baseline_m, Perturb(scene.T_cam_world_true, 0.05, 3.0, rng), scene.observations,
                   PoseOptimizerOptions{});
  ASSERT_TRUE(r.success);
  EXPECT_EQ(r.num_inliers, 60);
  EXPECT_LT((r.T_cam_world.matrix() - scene.T_cam_world_true.matrix()).norm(), 1e-6);
}

TEST(OptimizePose, TooFewObservationsFailsAsValue) {
  const PoseScene scene = MakePoseScene(2, 0.0, false, 4);
  const Eigen::Isometry3d T_init = scene.T_cam_world_true;
  const PoseOptimizationResult r =
      OptimizePose(scene.camera, scene.baseline_m, T_init, scene.observations, PoseOptimizerOptions{});
  EXPECT_FALSE(r.success);
  EXPECT_TRUE(r.T_cam_world.matrix() == T_init.matrix());
  EXPECT_EQ(r.inlier.size(), 2u);
}

TEST(OptimizePose, RejectsMisuse) {
  PoseScene scene = MakePoseScene(10, 0.0, true, 5);
  PoseOptimizerOptions bad;
  bad.rounds = 0;
  EXPECT_FALSE(bad.Check());
  EXPECT_THROW((void)OptimizePose(scene.camera, scene.baseline_m, scene.T_cam_world_true, scene.observations, bad),
               Error);
  EXPECT_THROW((void)OptimizePose(scene.camera, 0.0, scene.T_cam_world_true, scene.observations, {}), Error);
  scene.observations[0].inv_sigma2 = 0;
  EXPECT_THROW((void)OptimizePose(scene.camera, scene.baseline_m, scene.T_cam_world_true, scene.observations, {}),
               Error);
}

TEST(PoseManifold, PlusAndMinusAreInverse) {
  const std::unique_ptr<ceres::Manifold> manifold = detail::MakePoseManifold();
  std::mt19937_64 rng(9);
  const Eigen::Isometry3d T = Perturb(Eigen::Isometry3d::Identity(), 1.0, 40.0, rng);
  double x[7], y[7], back[6];
  detail::PoseToParameters(T, x);
  const double delta[6] = {0.1, -0.2, 0.05, 0.3, -0.1, 0.2};
  ASSERT_TRUE(manifold->Plus(x, delta, y));
  ASSERT_TRUE(manifold->Minus(y, x, back));
  for (int k = 0; k < 6; ++k) EXPECT_NEAR(back[k], delta[k], 1e-12);
  // Plus is a left perturbation: T' = Exp(delta) T.
  const Eigen::Isometry3d T_plus = detail::ParametersToPose(y);
  const Eigen::Vector3d X(0.3, -1.0, 2.0);
  const Eigen::Matrix3d dR =
      Eigen::AngleAxisd(Eigen::Vector3d(0.1, -0.2, 0.05).norm(), Eigen::Vector3d(0.1, -0.2, 0.05).normalized())
          .toRotationMatrix();
  EXPECT_LT((T_plus * X - (dR * (T * X) + Eigen::Vector3d(0.3, -0.1, 0.2))).norm(), 1e-12);
}

}  // namespace
}  // namespace flatslam
