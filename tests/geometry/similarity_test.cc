// Sim(3)/SE(3) alignment, RANSAC with outliers and the essential-graph optimization.
#include "geometry/similarity.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "geometry/geometry_fixtures.h"

namespace flatslam {
namespace {

using testing::kDeg;
using testing::RandomUnit;
using testing::RotationErrorDeg;
using testing::TestCamera;

Similarity3 MakeSim(double angle, const Eigen::Vector3d& axis, const Eigen::Vector3d& t, double s) {
  return {Eigen::AngleAxisd(angle, axis.normalized()).toRotationMatrix(), t, s};
}

TEST(AlignPointsTest, RecoversSimilarityExactly) {
  std::mt19937_64 rng(3);
  const Similarity3 truth = MakeSim(40 * kDeg, {0.3, 1, -0.2}, {0.5, -1.2, 2.0}, 1.7);
  std::vector<Eigen::Vector3d> X1, X2;
  for (int k = 0; k < 20; ++k) {
    X1.push_back(3.0 * RandomUnit(rng));
    X2.push_back(truth * X1.back());
  }
  const auto S = AlignPoints(X1, X2, false);
  ASSERT_TRUE(S.has_value());
  EXPECT_NEAR(S->s, 1.7, 1e-9);
  EXPECT_LT(RotationErrorDeg(S->R, truth.R), 1e-6);
  EXPECT_LT((S->t - truth.t).norm(), 1e-9);
  const auto fixed = AlignPoints(X1, X2, true);
  ASSERT_TRUE(fixed.has_value());
  EXPECT_DOUBLE_EQ(fixed->s, 1.0);
}

TEST(AlignPointsTest, RejectsDegenerateSets) {
  const std::vector<Eigen::Vector3d> line = {{0, 0, 1}, {0, 0, 2}, {0, 0, 3}};
  EXPECT_FALSE(AlignPoints(line, line, false).has_value());
  const std::vector<Eigen::Vector3d> two = {{0, 0, 1}, {1, 0, 2}};
  EXPECT_FALSE(AlignPoints(two, two, false).has_value());
}

TEST(AlignPointsTest, InverseAndComposition) {
  const Similarity3 a = MakeSim(20 * kDeg, {1, 0, 0}, {1, 2, 3}, 0.5);
  const Similarity3 b = MakeSim(-35 * kDeg, {0, 1, 1}, {-1, 0, 2}, 2.5);
  const Eigen::Vector3d X(0.3, -0.7, 4.0);
  EXPECT_LT(((a * b) * X - a * (b * X)).norm(), 1e-12);
  EXPECT_LT((a.inverse() * (a * X) - X).norm(), 1e-12);
}

// Points seen by two cameras; camera 2's frame relates to camera 1's by S_21, some matches wrong.
std::vector<PointCorrespondence> MakeMatches(const Similarity3& S_21, int inliers, int outliers, std::mt19937_64& rng) {
  const PinholeCamera cam = TestCamera();
  std::uniform_real_distribution<double> u(-1.5, 1.5), z(3, 8);
  std::normal_distribution<double> px(0, 0.5);
  std::vector<PointCorrespondence> out;
  auto project = [&](const Eigen::Vector3d& X) {
    return Eigen::Vector2d(cam.fx * X.x() / X.z() + cam.cx + px(rng), cam.fy * X.y() / X.z() + cam.cy + px(rng));
  };
  while (static_cast<int>(out.size()) < inliers) {
    PointCorrespondence c;
    c.X1 = Eigen::Vector3d(u(rng), u(rng), z(rng));
    c.X2 = S_21 * c.X1;
    if (c.X2.z() <= 0.5) continue;
    c.uv1 = project(c.X1);
    c.uv2 = project(c.X2);
    out.push_back(c);
  }
  for (int k = 0; k < outliers; ++k) {
    PointCorrespondence c = out[k];
    c.X2 = S_21 * Eigen::Vector3d(u(rng), u(rng), z(rng));  // a different point
    c.uv2 = project(c.X2);
    c.X1 = out[(k + 7) % inliers].X1;
    c.uv1 = project(c.X1);
    out.push_back(c);
  }
  std::shuffle(out.begin(), out.end(), rng);
  return out;
}

TEST(SimilarityRansacTest, FindsSim3AmongOutliers) {
  std::mt19937_64 rng(11);
  const Similarity3 truth = MakeSim(15 * kDeg, {0, 1, 0}, {0.4, 0.1, 0.3}, 0.8);
  const auto matches = MakeMatches(truth, 60, 40, rng);
  const auto result = EstimateSimilarityRansac(TestCamera(), matches, SimilarityRansacOptions{}, rng);
  ASSERT_TRUE(result.has_value());
  EXPECT_GE(result->num_inliers, 55);
  EXPECT_LE(result->num_inliers, 66);  // a few outliers may land within the gate by chance
  EXPECT_NEAR(result->S_21.s, 0.8, 0.02);
  EXPECT_LT(RotationErrorDeg(result->S_21.R, truth.R), 0.5);
  EXPECT_LT((result->S_21.t - truth.t).norm(), 0.05);
}

TEST(SimilarityRansacTest, Se3KeepsUnitScale) {
  std::mt19937_64 rng(12);
  const Similarity3 truth = MakeSim(-10 * kDeg, {1, 1, 0}, {-0.3, 0.2, 0.5}, 1.0);
  const auto matches = MakeMatches(truth, 50, 30, rng);
  SimilarityRansacOptions options;
  options.fix_scale = true;
  const auto result = EstimateSimilarityRansac(TestCamera(), matches, options, rng);
  ASSERT_TRUE(result.has_value());
  EXPECT_DOUBLE_EQ(result->S_21.s, 1.0);
  EXPECT_LT((result->S_21.t - truth.t).norm(), 0.05);
}

TEST(SimilarityRansacTest, FailsWithoutConsensus) {
  std::mt19937_64 rng(13);
  const auto matches = MakeMatches(MakeSim(0, {0, 0, 1}, {0, 0, 0}, 1), 10, 40, rng);
  SimilarityRansacOptions options;
  options.min_inliers = 20;
  EXPECT_FALSE(EstimateSimilarityRansac(TestCamera(), matches, options, rng).has_value());
}

// A ring of poses: odometry edges with a small drift in each step, plus one loop edge measured
// without drift. The optimization must pull the accumulated error back.
TEST(PoseGraphTest, LoopEdgeRemovesDrift) {
  const int n = 40;
  std::vector<Similarity3> truth;  // S_cw of poses on a circle of radius 5, looking outwards
  for (int k = 0; k < n; ++k) {
    const double a = 2 * testing::kPi * k / n;
    Eigen::Isometry3d T_wc = Eigen::Isometry3d::Identity();
    T_wc.linear() = Eigen::AngleAxisd(a, Eigen::Vector3d::UnitY()).toRotationMatrix();
    T_wc.translation() = Eigen::Vector3d(5 * std::cos(a), 0, 5 * std::sin(a));
    truth.push_back(Similarity3::FromIsometry(T_wc.inverse()));
  }
  for (bool fix_scale : {true, false}) {
    // Odometry with a bias: each step's measurement is off by a small rotation and a scale drift.
    const Similarity3 bias = MakeSim(0.4 * kDeg, {0, 1, 0.2}, {0.02, 0, 0}, fix_scale ? 1.0 : 1.01);
    std::vector<PoseGraphEdge> edges;
    std::vector<Similarity3> drifted = {truth[0]};
    for (int k = 1; k < n; ++k) {
      const Similarity3 S_k_km1 = bias * (truth[k] * truth[k - 1].inverse());
      edges.push_back({static_cast<uint32_t>(k), static_cast<uint32_t>(k - 1), S_k_km1, 1.0});
      drifted.push_back(S_k_km1 * drifted.back());
    }
    edges.push_back({static_cast<uint32_t>(n - 1), 0, truth[n - 1] * truth[0].inverse(), 1.0});
    auto center_error = [&](const std::vector<Similarity3>& S) {
      double worst = 0;
      for (int k = 0; k < n; ++k) worst = std::max(worst, (S[k].inverse().t - truth[k].inverse().t).norm());
      return worst;
    };
    const double before = center_error(drifted);
    std::vector<bool> fixed(n, false);
    fixed[0] = true;
    PoseGraphOptions options;
    options.fix_scale = fix_scale;
    options.iterations = 50;
    OptimizePoseGraph(drifted, fixed, edges, options);
    const double after = center_error(drifted);
    EXPECT_GT(before, 1.0) << "fix_scale " << fix_scale;
    EXPECT_LT(after, before / 4) << "fix_scale " << fix_scale;
  }
}

}  // namespace
}  // namespace flatslam
