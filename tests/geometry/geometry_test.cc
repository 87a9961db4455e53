#include "geometry/geometry.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "core/error.h"
#include "geometry/geometry_fixtures.h"

namespace flatslam {
namespace {

using testing::kDeg;
using testing::kPi;
using testing::Pose;
using testing::RandomUnit;
using testing::RotationErrorDeg;
using testing::TestCamera;

Eigen::Matrix3d Rot(double angle_rad, const Eigen::Vector3d& axis) {
  return Eigen::AngleAxisd(angle_rad, axis.normalized()).toRotationMatrix();
}

Eigen::Vector2d Project(const PinholeCamera& c, const Eigen::Vector3d& x_cam) {
  return {c.fx * x_cam.x() / x_cam.z() + c.cx, c.fy * x_cam.y() / x_cam.z() + c.cy};
}

bool InImage(const PinholeCamera& c, const Eigen::Vector2d& px) {
  return px.x() >= 0 && px.y() >= 0 && px.x() < c.width && px.y() < c.height;
}

double DirectionErrorDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::acos(std::clamp(a.normalized().dot(b.normalized()), -1.0, 1.0)) / kDeg;
}

TEST(TriangulateDlt, NoiseFreePointsAreExact) {
  const PinholeCamera camera = TestCamera();
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int trial = 0; trial < 200; ++trial) {
    const Eigen::Isometry3d T1 = Pose(Rot(0.3 * u(rng), {u(rng), u(rng), u(rng)}), {u(rng), u(rng), u(rng)});
    const Eigen::Isometry3d T2 = Pose(Rot(0.3 * u(rng), {u(rng), u(rng), u(rng)}), {u(rng), u(rng), u(rng)});
    // A point in front of camera 1 at 2..10 m.
    const Eigen::Vector3d x1_cam(2 * u(rng), 2 * u(rng), 6 + 4 * u(rng));
    const Eigen::Vector3d X = T1.inverse() * x1_cam;
    if ((T2 * X).z() <= 0.5) continue;
    const Eigen::Matrix<double, 3, 4> P1 = camera.K() * T1.matrix().topRows<3>();
    const Eigen::Matrix<double, 3, 4> P2 = camera.K() * T2.matrix().topRows<3>();
    const std::optional<Eigen::Vector3d> X_dlt =
        TriangulateDlt(P1, P2, Project(camera, T1 * X), Project(camera, T2 * X));
    ASSERT_TRUE(X_dlt.has_value());
    EXPECT_LT((*X_dlt - X).norm(), 1e-9) << "trial " << trial;

    TriangulationOptions options;
    options.min_parallax_deg = 0;
    const TriangulatedPoint p =
        TriangulatePoint(camera, T1, T2, Project(camera, T1 * X), Project(camera, T2 * X), options);
    EXPECT_EQ(p.status, TriangulationStatus::kOk);
    EXPECT_LT((p.X_world - X).norm(), 1e-9);
    EXPECT_LT(p.max_error_px, 1e-6);
  }
}

TEST(TriangulatePoint, RejectsPointsBehindTheCamera) {
  const PinholeCamera camera = TestCamera();
  const Eigen::Isometry3d T1 = Eigen::Isometry3d::Identity();
  const Eigen::Isometry3d T2 = Pose(Rot(2 * kDeg, Eigen::Vector3d::UnitY()), {-0.5, 0, 0});
  const Eigen::Vector3d X(0.3, -0.2, -5);  // behind both cameras, still projects to pixels
  const TriangulatedPoint p =
      TriangulatePoint(camera, T1, T2, Project(camera, T1 * X), Project(camera, T2 * X), TriangulationOptions{});
  EXPECT_EQ(p.status, TriangulationStatus::kBehindCamera);
  EXPECT_FALSE(p.ok());
  EXPECT_LT((p.X_world - X).norm(), 1e-9);  // the intersection itself is still exact
}

TEST(TriangulatePoint, RejectsLowParallaxAndLargeError) {
  const PinholeCamera camera = TestCamera();
  const Eigen::Isometry3d T1 = Eigen::Isometry3d::Identity();
  const Eigen::Isometry3d T2 = Pose(Eigen::Matrix3d::Identity(), {-0.1, 0, 0});
  const Eigen::Vector3d far(0.5, 0.2, 50);  // 0.1 m baseline at 50 m: ~0.11 degrees
  TriangulatedPoint p =
      TriangulatePoint(camera, T1, T2, Project(camera, T1 * far), Project(camera, T2 * far), TriangulationOptions{});
  EXPECT_EQ(p.status, TriangulationStatus::kLowParallax);
  EXPECT_NEAR(p.parallax_deg, 0.1 / 50 / kDeg, 0.01);

  const Eigen::Vector3d near(0.5, 0.2, 3);
  p = TriangulatePoint(camera, T1, T2, Project(camera, T1 * near), Project(camera, T2 * near) + Eigen::Vector2d(0, 8),
                       TriangulationOptions{});
  EXPECT_EQ(p.status, TriangulationStatus::kLargeError);
}

// Matched pixels of a scene seen from view 1 (identity) and view 2 (T_2_1), with Gaussian
// noise on inliers and a fraction of random (gross) mismatches.
struct Correspondences {
  std::vector<Eigen::Vector2d> px1, px2;
  std::vector<Eigen::Vector3d> X1;  // true points in view-1 coordinates
  std::vector<bool> is_outlier;
};

Correspondences MakeCorrespondences(const PinholeCamera& camera, const Eigen::Isometry3d& T_2_1,
                                    const std::vector<Eigen::Vector3d>& points, double noise_px,
                                    double outlier_fraction, std::mt19937_64& rng) {
  std::normal_distribution<double> noise(0, noise_px);
  std::uniform_real_distribution<double> unit(0, 1);
  Correspondences c;
  for (const Eigen::Vector3d& X : points) {
    const Eigen::Vector3d X2 = T_2_1 * X;
    if (X.z() <= 0.1 || X2.z() <= 0.1) continue;
    Eigen::Vector2d p1 = Project(camera, X), p2 = Project(camera, X2);
    if (!InImage(camera, p1) || !InImage(camera, p2)) continue;
    const bool outlier = unit(rng) < outlier_fraction;
    if (outlier) {
      p2 = Eigen::Vector2d(unit(rng) * camera.width, unit(rng) * camera.height);
    } else {
      p1 += Eigen::Vector2d(noise(rng), noise(rng));
      p2 += Eigen::Vector2d(noise(rng), noise(rng));
    }
    c.px1.push_back(p1);
    c.px2.push_back(p2);
    c.X1.push_back(X);
    c.is_outlier.push_back(outlier);
  }
  return c;
}

void ExpectMotionRecovered(const TwoViewResult& r, const Eigen::Isometry3d& T_2_1, const Correspondences& c) {
  const double rot_err = RotationErrorDeg(r.T_2_1.linear(), T_2_1.linear());
  const double dir_err = DirectionErrorDeg(r.T_2_1.translation(), T_2_1.translation());
  printf(
      "  rotation error %.3f deg, translation direction error %.3f deg, inliers %d/%zu, triangulated %d, "
      "parallax %.2f deg, RH %.3f\n",
      rot_err, dir_err, r.inliers, c.px1.size(), r.num_triangulated, r.parallax_deg, r.homography_ratio);
  EXPECT_LT(rot_err, 0.5);
  EXPECT_LT(dir_err, 2.0);
  ASSERT_EQ(r.points.size(), c.px1.size());
  ASSERT_EQ(r.triangulated.size(), c.px1.size());
  // Triangulated points sit at the true positions up to the median-depth scale; no outlier survives.
  std::vector<double> depths;
  int outliers_triangulated = 0;
  for (size_t i = 0; i < c.px1.size(); ++i) {
    if (!r.triangulated[i]) continue;
    depths.push_back(r.points[i].z());
    outliers_triangulated += c.is_outlier[i];
  }
  ASSERT_FALSE(depths.empty());
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
  EXPECT_NEAR(depths[depths.size() / 2], 1.0, 1e-9);
  const double scale = r.T_2_1.translation().norm() / T_2_1.translation().norm();
  double sum_rel = 0;
  int count = 0;
  for (size_t i = 0; i < c.px1.size(); ++i) {
    if (!r.triangulated[i] || c.is_outlier[i]) continue;
    sum_rel += (r.points[i] / scale - c.X1[i]).norm() / c.X1[i].norm();
    ++count;
  }
  EXPECT_LT(sum_rel / count, 0.05) << "mean relative point error";
  EXPECT_LE(outliers_triangulated, static_cast<int>(0.02 * c.px1.size()));
  EXPECT_GT(r.num_triangulated, static_cast<int>(0.6 * c.px1.size()));
}

// A general 3D scene: points in a box 2.5..7.5 m ahead of view 1.
std::vector<Eigen::Vector3d> BoxScene(int n, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Eigen::Vector3d> points;
  for (int i = 0; i < n; ++i) points.emplace_back(3 * u(rng), 2 * u(rng), 5 + 2.5 * u(rng));
  return points;
}

// A plane tilted 45 degrees (like a floor or a table seen obliquely), 2.5..5.5 m ahead.
std::vector<Eigen::Vector3d> PlaneScene(int n, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(-1, 1);
  std::vector<Eigen::Vector3d> points;
  for (int i = 0; i < n; ++i) {
    const double x = 3 * u(rng), y = 1.5 * u(rng);
    points.emplace_back(x, y, 4 + y);
  }
  return points;
}

TEST(InitializeTwoView, GeneralSceneSelectsFundamental) {
  const PinholeCamera camera = TestCamera();
  std::mt19937_64 rng(11);
  const std::vector<Eigen::Vector3d> points = BoxScene(400, rng);
  const Eigen::Isometry3d T_2_1 = Pose(Rot(4 * kDeg, {0.2, 1, 0.1}), {-0.5, 0.05, 0.1});
  const Correspondences c = MakeCorrespondences(camera, T_2_1, points, 1.0, 0.2, rng);
  ASSERT_GT(c.px1.size(), 200u);
  std::mt19937_64 ransac_rng(3);
  const TwoViewOptions options;
  const auto start = std::chrono::steady_clock::now();
  const std::optional<TwoViewResult> r = InitializeTwoView(c.px1, c.px2, camera, options, ransac_rng);
  printf("  InitializeTwoView on %zu matches: %.1f ms\n", c.px1.size(),
         std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count());
  ASSERT_TRUE(r.has_value());
  EXPECT_FALSE(r->used_homography);
  EXPECT_LT(r->homography_ratio, options.homography_ratio);
  ExpectMotionRecovered(*r, T_2_1, c);
}

TEST(InitializeTwoView, PlanarSceneSelectsHomography) {
  const PinholeCamera camera = TestCamera();
  std::mt19937_64 rng(12);
  const std::vector<Eigen::Vector3d> points = PlaneScene(400, rng);
  const Eigen::Isometry3d T_2_1 = Pose(Rot(3 * kDeg, {-0.3, 1, 0.2}), {-0.8, 0.1, 0.05});
  const Correspondences c = MakeCorrespondences(camera, T_2_1, points, 1.0, 0.2, rng);
  ASSERT_GT(c.px1.size(), 200u);
  std::mt19937_64 ransac_rng(4);
  const TwoViewOptions options;
  const std::optional<TwoViewResult> r = InitializeTwoView(c.px1, c.px2, camera, options, ransac_rng);
  ASSERT_TRUE(r.has_value());
  EXPECT_TRUE(r->used_homography);
  EXPECT_GT(r->homography_ratio, options.homography_ratio);  // selected by the score ratio itself
  ExpectMotionRecovered(*r, T_2_1, c);
}

TEST(InitializeTwoView, PureRotationHasNoSolution) {
  const PinholeCamera camera = TestCamera();
  std::mt19937_64 rng(13);
  const std::vector<Eigen::Vector3d> points = BoxScene(400, rng);
  const Eigen::Isometry3d T_2_1 = Pose(Rot(5 * kDeg, {0.1, 1, 0.1}), Eigen::Vector3d::Zero());
  const Correspondences c = MakeCorrespondences(camera, T_2_1, points, 1.0, 0.2, rng);
  std::mt19937_64 ransac_rng(5);
  const std::optional<TwoViewResult> r = InitializeTwoView(c.px1, c.px2, camera, TwoViewOptions{}, ransac_rng);
  EXPECT_FALSE(r.has_value());
}

// Many random motions (rotation about a random axis, mostly sideways translation): success
// rate and error statistics, so the single-seed tests above are not a lucky draw.
TEST(InitializeTwoView, RobustOverManyScenes) {
  const PinholeCamera camera = TestCamera();
  constexpr int kScenes = 30;
  int solved[2] = {0, 0}, rotation_solved = 0, wrong_model = 0;
  std::vector<double> rot_err[2], dir_err[2];
  for (int seed = 0; seed < kScenes; ++seed) {
    std::mt19937_64 rng(1000 + seed);
    std::uniform_real_distribution<double> u(-1, 1);
    for (int kind = 0; kind < 3; ++kind) {
      const std::vector<Eigen::Vector3d> points = kind == 1 ? PlaneScene(400, rng) : BoxScene(400, rng);
      const Eigen::Vector3d axis(u(rng), 1, u(rng));
      const Eigen::Isometry3d T_2_1 =
          kind == 2 ? Pose(Rot(5 * kDeg, axis), Eigen::Vector3d::Zero())
                    : Pose(Rot(4 * kDeg, axis), Eigen::Vector3d(-0.5, 0.1 * u(rng), 0.1 * u(rng)));
      const Correspondences c = MakeCorrespondences(camera, T_2_1, points, 1.0, 0.2, rng);
      std::mt19937_64 ransac_rng(seed);
      const std::optional<TwoViewResult> r = InitializeTwoView(c.px1, c.px2, camera, TwoViewOptions{}, ransac_rng);
      if (kind == 2) {
        rotation_solved += r.has_value();
        continue;
      }
      if (!r) continue;
      ++solved[kind];
      wrong_model += r->used_homography != (kind == 1);
      rot_err[kind].push_back(RotationErrorDeg(r->T_2_1.linear(), T_2_1.linear()));
      dir_err[kind].push_back(DirectionErrorDeg(r->T_2_1.translation(), T_2_1.translation()));
    }
  }
  auto percentile = [](std::vector<double> v, double p) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 0.0 : v[static_cast<size_t>(p * (v.size() - 1))];
  };
  for (int kind = 0; kind < 2; ++kind) {
    printf(
        "  %s: solved %d/%d, rotation error median %.3f p90 %.3f max %.3f deg, translation direction median "
        "%.3f p90 %.3f max %.3f deg\n",
        kind == 0 ? "general" : "planar", solved[kind], kScenes, percentile(rot_err[kind], 0.5),
        percentile(rot_err[kind], 0.9), percentile(rot_err[kind], 1.0), percentile(dir_err[kind], 0.5),
        percentile(dir_err[kind], 0.9), percentile(dir_err[kind], 1.0));
    EXPECT_GE(solved[kind], kScenes - 2);
    EXPECT_LT(percentile(rot_err[kind], 0.5), 0.25);
    EXPECT_LT(percentile(rot_err[kind], 1.0), 1.0);
    EXPECT_LT(percentile(dir_err[kind], 0.5), 1.5);
  }
  printf("  pure rotation: solved %d/%d (must be 0); wrong model %d\n", rotation_solved, kScenes, wrong_model);
  EXPECT_EQ(rotation_solved, 0);
  EXPECT_EQ(wrong_model, 0);
}

TEST(InitializeTwoView, IsDeterministicGivenTheSeed) {
  const PinholeCamera camera = TestCamera();
  std::mt19937_64 rng(14);
  const std::vector<Eigen::Vector3d> points = BoxScene(300, rng);
  const Eigen::Isometry3d T_2_1 = Pose(Rot(4 * kDeg, {0.2, 1, 0.1}), {-0.5, 0.05, 0.1});
  const Correspondences c = MakeCorrespondences(camera, T_2_1, points, 1.0, 0.2, rng);
  std::mt19937_64 a(99), b(99);
  const auto ra = InitializeTwoView(c.px1, c.px2, camera, TwoViewOptions{}, a);
  const auto rb = InitializeTwoView(c.px1, c.px2, camera, TwoViewOptions{}, b);
  ASSERT_TRUE(ra && rb);
  EXPECT_TRUE(ra->T_2_1.matrix() == rb->T_2_1.matrix());
  EXPECT_EQ(ra->triangulated, rb->triangulated);
}

TEST(InitializeTwoView, RejectsMisuseAndTooFewPoints) {
  const PinholeCamera camera = TestCamera();
  std::mt19937_64 rng(1);
  std::vector<Eigen::Vector2d> a(10, Eigen::Vector2d(1, 2)), b(9, Eigen::Vector2d(1, 2));
  EXPECT_THROW((void)InitializeTwoView(a, b, camera, TwoViewOptions{}, rng), Error);
  TwoViewOptions bad;
  bad.homography_ratio = 1.5;
  EXPECT_FALSE(bad.Check());
  EXPECT_THROW((void)InitializeTwoView(a, a, camera, bad, rng), Error);
  const std::vector<Eigen::Vector2d> few(5, Eigen::Vector2d(1, 2));
  EXPECT_FALSE(InitializeTwoView(few, few, camera, TwoViewOptions{}, rng).has_value());
}

// A motion continued at its constant twist: twice it is the motion applied twice, half of it
// applied twice is the motion, none of it is the identity; a pure translation scales linearly;
// small and large rotations alike.
TEST(ScaledMotion, ContinuesTheConstantTwist) {
  for (const double angle : {0.0, 1e-7, 1e-3, 0.3, 2.5}) {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Rot(angle, Eigen::Vector3d(0.3, -1.0, 0.2));
    T.translation() = Eigen::Vector3d(0.4, -0.1, 1.3);
    const Eigen::Isometry3d twice = ScaledMotion(T, 2.0), half = ScaledMotion(T, 0.5);
    EXPECT_LT(((T * T).matrix() - twice.matrix()).norm(), 1e-9) << angle;
    EXPECT_LT(((half * half).matrix() - T.matrix()).norm(), 1e-9) << angle;
    EXPECT_LT((ScaledMotion(T, 1.0).matrix() - T.matrix()).norm(), 1e-9) << angle;
    EXPECT_LT((ScaledMotion(T, 0.0).matrix() - Eigen::Matrix4d::Identity()).norm(), 1e-12) << angle;
    EXPECT_LT(((T * T * T).matrix() - ScaledMotion(T, 3.0).matrix()).norm(), 1e-9) << angle;
  }
  Eigen::Isometry3d shift = Eigen::Isometry3d::Identity();
  shift.translation() = Eigen::Vector3d(1.0, 2.0, -3.0);
  EXPECT_LT((ScaledMotion(shift, 1.7).translation() - 1.7 * shift.translation()).norm(), 1e-12);
}

}  // namespace
}  // namespace flatslam
