#include "trajectory/metrics.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

#include "core/error.h"
#include "test_data.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

std::filesystem::path TrajectoriesDir() {
  return testing::DatasetsDir() / "trajectories";
}

Eigen::Isometry3d Pose(const Eigen::Matrix3d& r, const Eigen::Vector3d& t) {
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  pose.linear() = r;
  pose.translation() = t;
  return pose;
}

Eigen::Matrix3d RotZ(double a) {
  return Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()).toRotationMatrix();
}

// A 3D helix with turning orientation, 10 Hz: spread in every axis, so alignment is well posed.
Trajectory Helix(size_t n) {
  Trajectory trajectory;
  for (size_t i = 0; i < n; ++i) {
    const double a = 0.05 * static_cast<double>(i);
    TimedPose p;
    p.t_ns = static_cast<int64_t>(i) * 100'000'000;
    p.T_world_cam = Pose(RotZ(a) * Eigen::AngleAxisd(0.3 * std::sin(a), Eigen::Vector3d::UnitX()),
                         Eigen::Vector3d(3 * std::cos(a), 2 * std::sin(a), 0.1 * a + 0.5 * std::sin(3 * a)));
    trajectory.push_back(p);
  }
  return trajectory;
}

std::vector<Eigen::Isometry3d> Poses(const Trajectory& trajectory) {
  std::vector<Eigen::Isometry3d> out;
  for (const auto& p : trajectory) out.push_back(p.T_world_cam);
  return out;
}

EvalOptions Aligned(Alignment alignment) {
  EvalOptions options;
  options.alignment = alignment;
  return options;
}

EvalOptions ByIndex() {
  EvalOptions options;
  options.pair_by_index = true;
  return options;
}

AssociationOptions MaxDiff(double max_diff_s, double est_offset_s = 0) {
  AssociationOptions options;
  options.max_diff_s = max_diff_s;
  options.est_offset_s = est_offset_s;
  return options;
}

// ---- Reference figures on published trajectories (evo's test data) ----

TEST(Metrics, Fr2DeskOrbMatchesEvo) {
  const Trajectory gt = ReadTrajectory(TrajectoriesDir() / "fr2_desk_groundtruth.txt");
  const Trajectory est = ReadTrajectory(TrajectoriesDir() / "fr2_desk_ORB.txt");
  const EvalResult r = Evaluate(gt, est, {});
  EXPECT_EQ(r.pairs.size(), 2225u);
  EXPECT_NEAR(r.ate_m.rmse, 0.0081, 0.00005);
  std::printf("fr2_desk ORB: %zu pairs, ATE rmse %.6f m\n", r.pairs.size(), r.ate_m.rmse);
}

TEST(Metrics, V102MatchesEvo) {
  const Trajectory gt = ReadTrajectory(TrajectoriesDir() / "V102_groundtruth.csv");
  const Trajectory est = ReadTrajectory(TrajectoriesDir() / "V102.txt");
  const EvalResult r = Evaluate(gt, est, {});
  EXPECT_EQ(r.pairs.size(), 798u);
  EXPECT_NEAR(r.ate_m.rmse, 0.0917, 0.00005);
  std::printf("V102: %zu pairs, ATE rmse %.6f m\n", r.pairs.size(), r.ate_m.rmse);
}

TEST(Metrics, ReferenceAssociationIteratesOverTheShorterTrajectory) {
  const Trajectory gt = ReadTrajectory(TrajectoriesDir() / "fr2_desk_groundtruth.txt");
  const Trajectory est = ReadTrajectory(TrajectoriesDir() / "fr2_desk_ORB.txt");
  ASSERT_LT(est.size(), gt.size());
  const auto pairs = AssociateByTime(gt, est);
  ASSERT_EQ(pairs.size(), 2225u);
  for (size_t k = 1; k < pairs.size(); ++k) EXPECT_GT(pairs[k].est_index, pairs[k - 1].est_index);
  for (const auto& p : pairs) EXPECT_LE(std::abs(gt[p.gt_index].t_ns - est[p.est_index].t_ns), 20'000'000);
}

// ---- Association ----

Trajectory AtTimes(const std::vector<int64_t>& times_ns) {
  Trajectory out;
  for (int64_t t : times_ns) out.push_back({t, Eigen::Isometry3d::Identity()});
  return out;
}

TEST(Associate, NearestWithinInclusiveTolerance) {
  const Trajectory gt = AtTimes({0, 10'000'000, 20'000'000, 30'000'000, 40'000'000, 50'000'000});
  // 20 ms away exactly: kept (inclusive); 20 ms + 1 ns: dropped.
  const Trajectory est = AtTimes({14'000'000, 70'000'000, 70'000'001});
  const auto pairs = AssociateByTime(gt, est);
  ASSERT_EQ(pairs.size(), 2u);
  EXPECT_EQ(pairs[0].est_index, 0u);
  EXPECT_EQ(pairs[0].gt_index, 1u);
  EXPECT_EQ(pairs[1].est_index, 1u);
  EXPECT_EQ(pairs[1].gt_index, 5u);
}

TEST(Associate, TieTakesTheFirstAndLongPosesMayRepeat) {
  const Trajectory gt = AtTimes({0, 10, 20, 30});
  const Trajectory est = AtTimes({5, 6});
  const auto pairs = AssociateByTime(gt, est, MaxDiff(1e-6));
  ASSERT_EQ(pairs.size(), 2u);
  EXPECT_EQ(pairs[0].gt_index, 0u);  // 5 is as far from 0 as from 10: first wins
  EXPECT_EQ(pairs[1].gt_index, 1u);
}

TEST(Associate, ShorterGroundTruthDrivesTheMatching) {
  // gt is shorter: each gt pose takes its nearest estimate, in gt order.
  const Trajectory gt = AtTimes({100, 200});
  const Trajectory est = AtTimes({90, 95, 130, 160, 199, 260});
  const auto pairs = AssociateByTime(gt, est, MaxDiff(1e-6));
  ASSERT_EQ(pairs.size(), 2u);
  EXPECT_EQ(pairs[0].gt_index, 0u);
  EXPECT_EQ(pairs[0].est_index, 1u);
  EXPECT_EQ(pairs[1].gt_index, 1u);
  EXPECT_EQ(pairs[1].est_index, 4u);
}

TEST(Associate, UnsortedAndOffset) {
  const Trajectory gt = AtTimes({3'000'000'000, 1'000'000'000, 2'000'000'000, 4'000'000'000});
  const Trajectory est = AtTimes({1'500'000'000, 500'000'000});
  const auto pairs = AssociateByTime(gt, est, MaxDiff(0.001, 0.5));
  ASSERT_EQ(pairs.size(), 2u);
  EXPECT_EQ(pairs[0].gt_index, 2u);
  EXPECT_EQ(pairs[1].gt_index, 1u);
}

TEST(Associate, ByIndexNeedsEqualLengths) {
  EXPECT_EQ(AssociateByIndex(AtTimes({0, 1, 2}), AtTimes({5, 6, 7})).size(), 3u);
  EXPECT_THROW((void)AssociateByIndex(AtTimes({0, 1, 2}), AtTimes({5, 6})), Error);
  EXPECT_THROW((void)AssociateByTime(AtTimes({}), AtTimes({5, 6})), Error);
}

// ---- Alignment and ATE ----

TEST(Align, UmeyamaRecoversAKnownSim3) {
  const Trajectory est = Helix(200);
  const Eigen::Matrix3d r = (Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized())).toRotationMatrix();
  const Eigen::Vector3d t(4, -5, 6);
  const double s = 2.5;
  Trajectory gt = est;
  for (auto& p : gt) {
    p.T_world_cam.linear() = r * p.T_world_cam.linear();
    p.T_world_cam.translation() = s * r * p.T_world_cam.translation() + t;
  }
  const EvalResult sim = Evaluate(gt, est, Aligned(Alignment::kSim3));
  EXPECT_EQ(sim.pairs.size(), 200u);
  EXPECT_NEAR(sim.alignment.scale, s, 1e-12);
  EXPECT_LT((sim.alignment.rotation - r).norm(), 1e-12);
  EXPECT_LT((sim.alignment.translation - t).norm(), 1e-11);
  EXPECT_LT(sim.ate_m.rmse, 1e-11);
  EXPECT_LT(sim.rpe_frames.translation_m.max, 1e-11);
  EXPECT_LT(sim.rpe_frames.rotation_deg.max, 1e-6);
  // Without scale the best fit leaves a large error.
  EXPECT_GT(Evaluate(gt, est, Aligned(Alignment::kSE3)).ate_m.rmse, 1.0);
}

TEST(Align, UmeyamaRecoversAKnownSE3) {
  const Trajectory est = Helix(150);
  const Eigen::Matrix3d r = (Eigen::AngleAxisd(-2.0, Eigen::Vector3d(0.2, -1, 0.5).normalized())).toRotationMatrix();
  const Eigen::Vector3d t(-1, 0.5, 10);
  Trajectory gt = est;
  for (auto& p : gt) p.T_world_cam = Pose(r, t) * p.T_world_cam;
  const EvalResult se3 = Evaluate(gt, est, Aligned(Alignment::kSE3));
  EXPECT_EQ(se3.alignment.scale, 1.0);
  EXPECT_LT((se3.alignment.rotation - r).norm(), 1e-12);
  EXPECT_LT((se3.alignment.translation - t).norm(), 1e-11);
  EXPECT_LT(se3.ate_m.max, 1e-11);
  EXPECT_GT(Evaluate(gt, est, Aligned(Alignment::kNone)).ate_m.rmse, 1.0);
}

TEST(Align, DegenerateSim3IsAValueAndEvaluateReportsIt) {
  const std::vector<Eigen::Vector3d> gt = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  const std::vector<Eigen::Vector3d> same = {{2, 2, 2}, {2, 2, 2}, {2, 2, 2}};
  EXPECT_FALSE(AlignUmeyama(gt, same, Alignment::kSim3).valid);
  EXPECT_TRUE(AlignUmeyama(gt, same, Alignment::kNone).valid);
  Trajectory est = Helix(3);
  for (auto& p : est) p.T_world_cam.translation().setConstant(2);
  EXPECT_THROW((void)Evaluate(Helix(3), est, Aligned(Alignment::kSim3)), Error);
}

TEST(Ate, PerturbationWithoutAlignmentGivesTheKnownErrors) {
  const Trajectory gt = Helix(100);
  Trajectory est = gt;
  const double offsets[4] = {0.1, 0.2, 0.3, 0.4};
  for (size_t i = 0; i < est.size(); ++i) {
    est[i].T_world_cam.translation() += Eigen::Vector3d(0, 0, (i % 2 ? -1 : 1) * offsets[i % 4]);
  }
  const ErrorStats ate = Evaluate(gt, est, Aligned(Alignment::kNone)).ate_m;
  EXPECT_EQ(ate.count, 100u);
  EXPECT_NEAR(ate.rmse, std::sqrt((0.01 + 0.04 + 0.09 + 0.16) / 4), 1e-12);
  EXPECT_NEAR(ate.mean, 0.25, 1e-12);
  EXPECT_NEAR(ate.median, 0.25, 1e-12);
  EXPECT_NEAR(ate.max, 0.4, 1e-12);
  EXPECT_NEAR(ate.min, 0.1, 1e-12);
  EXPECT_NEAR(ate.std, std::sqrt((0.0225 + 0.0025 + 0.0025 + 0.0225) / 4), 1e-12);
}

TEST(Ate, PerturbationThroughSE3AlignmentGivesTheKnownRmse) {
  // Each ground-truth position appears twice with opposite offsets +d, -d: the offsets have zero
  // mean and no correlation with the positions, so the best SE(3) is exactly the applied one
  // and the ATE is exactly |d|.
  const Trajectory helix = Helix(60);
  Trajectory gt, est;
  const Eigen::Isometry3d T = Pose(RotZ(1.1) * Eigen::AngleAxisd(0.4, Eigen::Vector3d::UnitY()), {3, -2, 1});
  double sum_sq = 0;
  for (size_t i = 0; i < helix.size(); ++i) {
    const Eigen::Vector3d d = 0.05 * Eigen::Vector3d(std::sin(1.3 * i), std::cos(0.7 * i), std::sin(2.9 * i + 1));
    for (double sign : {1.0, -1.0}) {
      TimedPose g = helix[i];
      g.t_ns = static_cast<int64_t>(gt.size()) * 50'000'000;
      TimedPose e = g;
      e.T_world_cam.translation() += sign * d;
      e.T_world_cam = T * e.T_world_cam;
      gt.push_back(g);
      est.push_back(e);
      sum_sq += d.squaredNorm();
    }
  }
  const EvalResult r = Evaluate(gt, est, Aligned(Alignment::kSE3));
  EXPECT_NEAR(r.ate_m.rmse, std::sqrt(sum_sq / static_cast<double>(gt.size())), 1e-12);
  EXPECT_LT((r.alignment.rotation - T.linear().transpose()).norm(), 1e-12);
}

TEST(ErrorStats, MedianStdOddAndEven) {
  ErrorStats odd = ComputeErrorStats({3, 1, 2});
  EXPECT_EQ(odd.median, 2);
  EXPECT_EQ(odd.count, 3u);
  ErrorStats even = ComputeErrorStats({4, 1, 3, 2});
  EXPECT_EQ(even.median, 2.5);
  EXPECT_DOUBLE_EQ(even.std, std::sqrt(1.25));
  EXPECT_DOUBLE_EQ(even.rmse, std::sqrt(7.5));
  EXPECT_EQ(ComputeErrorStats({}).count, 0u);
}

// ---- RPE ----

TEST(Rpe, ConstantPerStepDriftGivesConstantError) {
  // Ground truth: 1 m forward and 2 degrees of yaw per step. The estimate composes every
  // step with the same error D (2 cm sideways, 0.5 degree about a tilted axis).
  const Eigen::Isometry3d step = Pose(RotZ(2.0 * M_PI / 180), {1, 0, 0});
  const Eigen::Isometry3d drift = Pose(
      Eigen::AngleAxisd(0.5 * M_PI / 180, Eigen::Vector3d(0.3, 0.4, 1).normalized()).toRotationMatrix(), {0, 0.02, 0});
  Trajectory gt(50), est(50);
  for (size_t i = 1; i < gt.size(); ++i) {
    gt[i].t_ns = est[i].t_ns = static_cast<int64_t>(i) * 100'000'000;
    gt[i].T_world_cam = gt[i - 1].T_world_cam * step;
    est[i].T_world_cam = est[i - 1].T_world_cam * step * drift;
  }
  const RpeResult rpe = ComputeRpeFrames(Poses(gt), Poses(est), 1);
  EXPECT_EQ(rpe.pairs, 49u);
  EXPECT_NEAR(rpe.translation_m.mean, 0.02, 1e-12);
  EXPECT_NEAR(rpe.translation_m.max, 0.02, 1e-12);
  EXPECT_NEAR(rpe.translation_m.rmse, 0.02, 1e-12);
  EXPECT_NEAR(rpe.rotation_deg.min, 0.5, 1e-9);
  EXPECT_NEAR(rpe.rotation_deg.max, 0.5, 1e-9);
  // SE(3) alignment moves every pose alike and leaves the RPE unchanged.
  const EvalResult all = Evaluate(gt, est, Aligned(Alignment::kSE3));
  EXPECT_NEAR(all.rpe_frames.translation_m.rmse, 0.02, 1e-9);
  EXPECT_NEAR(all.rpe_frames.rotation_deg.rmse, 0.5, 1e-7);
}

TEST(Rpe, DistanceDeltaPairsAlongTheGroundTruthPath) {
  // Straight 1 m steps; the estimate is 10% too long. With delta 2.5 m the pairs are
  // (0,3), (3,6), ...: each 3 m long, so each is 0.3 m off and has no rotation error.
  Trajectory gt(31), est(31);
  for (size_t i = 0; i < gt.size(); ++i) {
    gt[i].T_world_cam.translation() = Eigen::Vector3d(static_cast<double>(i), 0, 0);
    est[i].T_world_cam.translation() = Eigen::Vector3d(1.1 * static_cast<double>(i), 0, 0);
  }
  const RpeResult rpe = ComputeRpeDistance(Poses(gt), Poses(est), 2.5);
  EXPECT_EQ(rpe.pairs, 10u);
  EXPECT_NEAR(rpe.translation_m.min, 0.3, 1e-12);
  EXPECT_NEAR(rpe.translation_m.max, 0.3, 1e-12);
  EXPECT_EQ(rpe.rotation_deg.max, 0.0);
  EXPECT_EQ(ComputeRpeDistance(Poses(gt), Poses(est), 100.0).pairs, 0u);
}

// ---- KITTI devkit metric ----

// A 1 km path: 0.5 m steps forward with a wobbling heading (the metric does not care).
Trajectory KilometrePath() {
  Trajectory gt(2001);
  for (size_t i = 0; i < gt.size(); ++i) {
    gt[i].t_ns = static_cast<int64_t>(i) * 100'000'000;
    gt[i].T_world_cam = Pose(RotZ(0.2 * std::sin(0.01 * i)), {0, 0, 0.5 * static_cast<double>(i)});
  }
  return gt;
}

TEST(KittiMetric, OnePercentScaleErrorGivesOnePercent) {
  const Trajectory gt = KilometrePath();
  Trajectory est = gt;
  for (auto& p : est) p.T_world_cam.translation() *= 1.01;
  const KittiMetricResult kitti = ComputeKittiMetric(Poses(gt), Poses(est));
  ASSERT_TRUE(kitti.available);
  EXPECT_NEAR(kitti.path_length_m, 1000.0, 1e-9);
  // Segments end at the first frame strictly beyond L, i.e. L + 0.5 m: 1% of (L + 0.5) / L.
  EXPECT_NEAR(kitti.t_rel_percent, 1.0, 0.005);
  EXPECT_GT(kitti.t_rel_percent, 1.0);
  EXPECT_LT(kitti.r_rel_deg_per_100m, 1e-9);
  // 20 start frames per 10 m: lengths 100..800 have 181, 161, ..., 41 start frames.
  size_t expected_segments = 0;
  for (int length = 100; length <= 800; length += 100) expected_segments += (2000 - 2 * length - 1) / 10 + 1;
  EXPECT_EQ(kitti.segments, expected_segments);
  // Sim(3) alignment removes the scale error.
  const EvalResult sim = Evaluate(gt, est, Aligned(Alignment::kSim3));
  EXPECT_LT(sim.kitti.t_rel_percent, 1e-9);
  EXPECT_NEAR(sim.alignment.scale, 1.0 / 1.01, 1e-12);
}

TEST(KittiMetric, KnownRotationDriftPerMetre) {
  // The estimate turns 0.001 deg more per 0.5 m step about the direction of travel, so a segment of
  // length L (L + 0.5 m walked) is (2 L + 1) * 0.001 degrees off.
  const Trajectory gt = KilometrePath();
  Trajectory est = gt;
  const double extra = 0.001 * M_PI / 180;
  for (size_t i = 0; i < est.size(); ++i) {
    est[i].T_world_cam.linear() =
        est[i].T_world_cam.linear() * Eigen::AngleAxisd(extra * i, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  }
  const KittiMetricResult kitti = ComputeKittiMetric(Poses(gt), Poses(est));
  double expected = 0;
  size_t segments = 0;
  for (int length = 100; length <= 800; length += 100) {
    const size_t starts = (2000 - 2 * length - 1) / 10 + 1;
    expected += static_cast<double>(starts) * (2 * length + 1) * 0.001 / length * 100;
    segments += starts;
  }
  EXPECT_NEAR(kitti.r_rel_deg_per_100m, expected / static_cast<double>(segments), 1e-9);
}

TEST(KittiMetric, NotAvailableBelowOneHundredMetres) {
  Trajectory gt = KilometrePath();
  gt.resize(200);  // 99.5 m
  const KittiMetricResult kitti = ComputeKittiMetric(Poses(gt), Poses(gt));
  EXPECT_FALSE(kitti.available);
  EXPECT_EQ(kitti.segments, 0u);
}

TEST(KittiMetric, RealKittiPosesAgainstThemselvesAreExact) {
  // KITTI files keep ~7 digits, so rotations are not quite orthonormal; identical poses must
  // still give zero error (general inverse, as the devkit).
  const Trajectory gt = ReadTrajectory(testing::DatasetsDir() / "kitti/poses/07.txt");
  EvalOptions options;
  options.alignment = Alignment::kNone;
  options.pair_by_index = true;
  options.kitti.lengths_m = {10, 20, 50};
  const EvalResult r = Evaluate(gt, gt, options);
  EXPECT_EQ(r.pairs.size(), 160u);
  ASSERT_TRUE(r.kitti.available);
  EXPECT_LT(r.kitti.t_rel_percent, 1e-9);
  EXPECT_LT(r.kitti.r_rel_deg_per_100m, 1e-6);
  EXPECT_LT(r.rpe_frames.rotation_deg.max, 1e-6);
  EXPECT_FALSE(Evaluate(gt, gt, ByIndex()).kitti.available);  // about 90 m
}

TEST(RotationAngle, AccurateAtSmallAndLargeAngles) {
  for (double a : {0.0, 1e-9, 1e-4, 0.5, 3.0, M_PI}) {
    EXPECT_NEAR(RotationAngle(Eigen::AngleAxisd(a, Eigen::Vector3d(1, -2, 0.5).normalized()).toRotationMatrix()), a,
                1e-12);
  }
}

}  // namespace
}  // namespace flatslam
