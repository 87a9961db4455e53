#include "optimization/bundle_adjustment.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>
#include <span>
#include <cstring>
#include <set>
#include <string>
#include <tuple>
#include <utility>

#include <gtest/gtest.h>
#include <tbb/parallel_for.h>

#include "core/cpu_features.h"
#include "core/error.h"
#include "geometry/geometry_fixtures.h"
#include "optimization/bundle_adjustment_lm.h"

namespace flatslam {
namespace {

using testing::kDeg;
using testing::kPi;
using testing::Pose;
using testing::RandomUnit;
using testing::TestCamera;

Eigen::Vector3d CameraCentre(const Eigen::Isometry3d& T_cam_world) {
  return T_cam_world.inverse().translation();
}

struct BaScene {
  BundleAdjustmentProblem truth;  // exact poses and points, noisy observations
  std::vector<bool> is_outlier;   // per observation
  double noise_rmse_px = 0;       // per-coordinate RMSE of the injected noise on inliers
};

// Keyframes 0.3 m apart along a gently turning path, looking at points 3..8 m ahead; every
// point that projects into a keyframe is observed there with 1 px noise times the octave scale.
// The first and last keyframes are fixed, as the window's neighbours would be in local BA.
BaScene MakeBaScene(int num_keyframes, int num_points, double outlier_fraction, bool stereo, uint64_t seed) {
  BaScene s;
  BundleAdjustmentProblem& p = s.truth;
  p.camera = TestCamera();
  p.baseline_m = 0.12;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(0, 1);
  std::normal_distribution<double> noise(0, 1);
  for (int k = 0; k < num_keyframes; ++k) {
    Eigen::Isometry3d T_world_cam = Eigen::Isometry3d::Identity();
    T_world_cam.linear() = (Eigen::AngleAxisd(0.02 * k, Eigen::Vector3d::UnitY()) *
                            Eigen::AngleAxisd(0.01 * std::sin(k), Eigen::Vector3d::UnitX()))
                               .toRotationMatrix();
    T_world_cam.translation() = Eigen::Vector3d(0.3 * k, 0.05 * std::sin(0.7 * k), 0.1 * k);
    p.poses.push_back({T_world_cam.inverse(), k == 0 || k == num_keyframes - 1});
  }
  for (int j = 0; j < num_points; ++j) p.points.emplace_back(-3 + 8 * unit(rng), -2 + 4 * unit(rng), 3 + 5 * unit(rng));
  const double bf = p.camera.fx * p.baseline_m;
  double sum_sigma2 = 0;
  int inliers = 0;
  for (int j = 0; j < num_points; ++j) {
    for (int k = 0; k < num_keyframes; ++k) {
      const Eigen::Vector3d x = p.poses[k].T_cam_world * p.points[j];
      if (x.z() <= 0.5) continue;
      const Eigen::Vector2d px(p.camera.fx * x.x() / x.z() + p.camera.cx, p.camera.fy * x.y() / x.z() + p.camera.cy);
      if (px.x() < 0 || px.y() < 0 || px.x() >= p.camera.width || px.y() >= p.camera.height) continue;
      BundleAdjustmentObservation obs;
      obs.pose_index = static_cast<uint32_t>(k);
      obs.point_index = static_cast<uint32_t>(j);
      const int octave = static_cast<int>(unit(rng) * 3);
      const double sigma = std::pow(1.2, octave);
      obs.inv_sigma2 = static_cast<float>(1.0 / (sigma * sigma));
      obs.uv = px + sigma * Eigen::Vector2d(noise(rng), noise(rng));
      if (stereo && x.z() < 8) obs.right_u = px.x() - bf / x.z() + sigma * noise(rng);
      const bool outlier = unit(rng) < outlier_fraction;
      if (outlier) {
        const double angle = 2 * kPi * unit(rng);
        obs.uv += (20 + 40 * unit(rng)) * Eigen::Vector2d(std::cos(angle), std::sin(angle));
        if (obs.right_u >= 0) obs.right_u = obs.uv.x() - bf / x.z();
      }
      p.observations.push_back(obs);
      s.is_outlier.push_back(outlier);
      if (!outlier) {
        sum_sigma2 += sigma * sigma;
        ++inliers;
      }
    }
  }
  s.noise_rmse_px = std::sqrt(sum_sigma2 / inliers);
  return s;
}

// Perturbs free poses by 5 cm (and 0.5 degrees) and all points by 10 cm.
BundleAdjustmentProblem Perturbed(const BundleAdjustmentProblem& truth, uint64_t seed) {
  BundleAdjustmentProblem p = truth;
  std::mt19937_64 rng(seed);
  for (BundleAdjustmentPose& pose : p.poses) {
    if (pose.fixed) continue;
    Eigen::Isometry3d T_world_cam = pose.T_cam_world.inverse();
    T_world_cam.translation() += 0.05 * RandomUnit(rng);
    T_world_cam.linear() = Eigen::AngleAxisd(0.5 * kDeg, RandomUnit(rng)).toRotationMatrix() * T_world_cam.linear();
    pose.T_cam_world = T_world_cam.inverse();
  }
  for (Eigen::Vector3d& X : p.points) X += 0.10 * RandomUnit(rng);
  return p;
}

using Solver = BundleAdjustmentOptions::Solver;

BundleAdjustmentOptions WithSolver(Solver solver) {
  BundleAdjustmentOptions options;
  options.solver = solver;
  return options;
}

void CheckRecovers(bool stereo, Solver solver) {
  const BaScene scene = MakeBaScene(10, 1000, 0.05, stereo, stereo ? 31 : 30);
  BundleAdjustmentProblem problem = Perturbed(scene.truth, 8);
  const BundleAdjustmentProblem before = problem;

  const auto start = std::chrono::steady_clock::now();
  const BundleAdjustmentResult r = LocalBundleAdjustment(problem, WithSolver(solver));
  const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  ASSERT_TRUE(r.success);
  ASSERT_EQ(r.outlier.size(), problem.observations.size());

  double max_pose_err = 0;
  for (size_t k = 0; k < problem.poses.size(); ++k) {
    if (problem.poses[k].fixed) {
      EXPECT_TRUE(problem.poses[k].T_cam_world.matrix() == before.poses[k].T_cam_world.matrix()) << "pose " << k;
      continue;
    }
    max_pose_err =
        std::max(max_pose_err,
                 (CameraCentre(problem.poses[k].T_cam_world) - CameraCentre(scene.truth.poses[k].T_cam_world)).norm());
  }
  int outliers = 0, flagged = 0, false_flags = 0;
  for (size_t i = 0; i < r.outlier.size(); ++i) {
    outliers += scene.is_outlier[i];
    flagged += scene.is_outlier[i] && r.outlier[i];
    false_flags += !scene.is_outlier[i] && r.outlier[i];
  }
  const int inliers = static_cast<int>(r.outlier.size()) - outliers;
  printf("  %s %s BA, %zu keyframes (first and last fixed), %zu points, %zu observations: %.1f ms, %d iterations\n",
         solver == Solver::kCeres ? "Ceres" : "Schur LM", stereo ? "stereo" : "mono", problem.poses.size(),
         problem.points.size(), problem.observations.size(), ms, r.iterations);
  printf(
      "  RMSE %.3f -> %.3f px (noise %.3f px), mean error %.3f px, max free-pose error %.2f mm, outliers "
      "flagged %d/%d, inliers flagged %d/%d\n",
      r.initial_rmse_px, r.final_rmse_px, scene.noise_rmse_px, r.final_mean_error_px, max_pose_err * 1e3, flagged,
      outliers, false_flags, inliers);
  EXPECT_GT(r.initial_rmse_px, 5 * scene.noise_rmse_px);
  // Down to the noise level (the chi2 gate trims the inlier tail, so slightly below it).
  EXPECT_LT(r.final_rmse_px, 1.05 * scene.noise_rmse_px);
  EXPECT_GT(r.final_rmse_px, 0.7 * scene.noise_rmse_px);
  EXPECT_LT(max_pose_err, 0.01);
  EXPECT_GE(flagged, static_cast<int>(0.95 * outliers));
  EXPECT_LT(false_flags, static_cast<int>(0.08 * inliers));
  EXPECT_EQ(r.num_outliers, flagged + false_flags);
}

TEST(LocalBundleAdjustment, MonoRecoversPosesAndFlagsOutliers) {
  CheckRecovers(false, Solver::kSchurLm);
}

TEST(LocalBundleAdjustment, StereoRecoversPosesAndFlagsOutliers) {
  CheckRecovers(true, Solver::kSchurLm);
}

TEST(LocalBundleAdjustment, CeresMonoRecoversPosesAndFlagsOutliers) {
  CheckRecovers(false, Solver::kCeres);
}

TEST(LocalBundleAdjustment, CeresStereoRecoversPosesAndFlagsOutliers) {
  CheckRecovers(true, Solver::kCeres);
}

TEST(LocalBundleAdjustment, SparseAndDenseSchurAgree) {
  for (Solver solver : {Solver::kSchurLm, Solver::kCeres}) {
    const BaScene scene = MakeBaScene(6, 300, 0.0, false, 40);
    BundleAdjustmentProblem dense = Perturbed(scene.truth, 9);
    BundleAdjustmentProblem sparse = dense;
    BundleAdjustmentOptions options = WithSolver(solver);
    options.linear_solver = BundleAdjustmentOptions::LinearSolver::kDenseSchur;
    const BundleAdjustmentResult rd = LocalBundleAdjustment(dense, options);
    options.linear_solver = BundleAdjustmentOptions::LinearSolver::kSparseSchur;
    const BundleAdjustmentResult rs = LocalBundleAdjustment(sparse, options);
    ASSERT_TRUE(rd.success && rs.success);
    EXPECT_NEAR(rd.final_rmse_px, rs.final_rmse_px, 1e-6);
    for (size_t k = 0; k < dense.poses.size(); ++k)
      EXPECT_LT((dense.poses[k].T_cam_world.matrix() - sparse.poses[k].T_cam_world.matrix()).norm(), 1e-6);
  }
}

// Conjugate gradients on the reduced camera system reach the minimum the sparse factorization
// reaches (to far below the noise), mono and stereo; their products split over threads give the
// same bits whatever the number of threads.
TEST(LocalBundleAdjustment, IterativeSchurReachesTheFactorizationsMinimum) {
  for (const auto& [stereo, inverse_depth] : {std::pair{false, 0}, {false, 2}, {true, 0}, {true, 1}, {true, 2}}) {
    SCOPED_TRACE("inverse_depth_points " + std::to_string(inverse_depth));
    const BaScene scene = MakeBaScene(30, 1500, 0.05, stereo, stereo ? 61 : 60);
    BundleAdjustmentProblem direct = Perturbed(scene.truth, 14);
    BundleAdjustmentProblem iterative = direct, threaded = direct;
    BundleAdjustmentOptions options = WithSolver(Solver::kSchurLm);
    options.inverse_depth_points = inverse_depth;
    options.first_pass_iterations = 10;
    options.second_pass_iterations = 20;
    options.linear_solver = BundleAdjustmentOptions::LinearSolver::kSparseSchur;
    const BundleAdjustmentResult rd = LocalBundleAdjustment(direct, options);
    options.linear_solver = BundleAdjustmentOptions::LinearSolver::kIterativeSchur;
    options.schur_lm_threads = 1;
    const BundleAdjustmentResult ri = LocalBundleAdjustment(iterative, options);
    options.schur_lm_threads = 3;
    const BundleAdjustmentResult rt = LocalBundleAdjustment(threaded, options);
    ASSERT_TRUE(rd.success && ri.success && rt.success);
    // The same outliers, but on at most one point: with a robust cost a point whose observations
    // include a gross error can have two local minima, each keeping a different subset of its
    // observations (in the monocular scene one point of 1500 does: each solve keeps another pair
    // of its four, 0.35 m apart along its ray).
    std::set<uint32_t> reclassified;
    for (size_t i = 0; i < rd.outlier.size(); ++i)
      if (rd.outlier[i] != ri.outlier[i]) reclassified.insert(direct.observations[i].point_index);
    EXPECT_LE(reclassified.size(), 1u) << (stereo ? "stereo" : "mono");
    EXPECT_NEAR(rd.final_rmse_px, ri.final_rmse_px, 1e-3 * scene.noise_rmse_px);
    EXPECT_LT(ri.final_rmse_px, 1.05 * scene.noise_rmse_px);
    // Against the truth: the iterative solve's camera centres as close as the direct one's (the
    // cost is flat along monocular depth-and-scale modes, where both stop at their own place).
    auto rms_error = [&](const BundleAdjustmentProblem& p) {
      double sum = 0;
      for (size_t k = 0; k < p.poses.size(); ++k)
        sum += (CameraCentre(p.poses[k].T_cam_world) - CameraCentre(scene.truth.poses[k].T_cam_world)).squaredNorm();
      return std::sqrt(sum / static_cast<double>(p.poses.size()));
    };
    for (size_t k = 0; k < direct.poses.size(); ++k)
      EXPECT_TRUE(iterative.poses[k].T_cam_world.matrix() == threaded.poses[k].T_cam_world.matrix()) << "pose " << k;
    const double direct_error = rms_error(direct), iterative_error = rms_error(iterative);
    std::printf("  %s: %d iterations direct, %d iterative; camera centres %.2f / %.2f mm from the truth (rms)\n",
                stereo ? "stereo" : "mono", rd.iterations, ri.iterations, direct_error * 1e3, iterative_error * 1e3);
    EXPECT_LT(iterative_error, 1.1 * direct_error + 1e-4);
    EXPECT_EQ(ri.outlier, rt.outlier);
    EXPECT_EQ(iterative.points, threaded.points);
  }
}

// flatslam's solver splits its passes over points into fixed slices: one thread, three, or those of
// the calling arena give the same bits, dense and sparse, mono and stereo, with outliers and with
// points in inverse depth. The threaded solves run inside a parallel loop of the caller's, as
// local mapping's run inside the tracking pipeline.
TEST(LocalBundleAdjustment, FactorizingSolversGiveTheSameBitsOnAnyNumberOfThreads) {
  using LinearSolver = BundleAdjustmentOptions::LinearSolver;
  for (const auto& [stereo, linear_solver, inverse_depth] :
       {std::tuple{false, LinearSolver::kDenseSchur, 0}, {true, LinearSolver::kDenseSchur, 1},
        {false, LinearSolver::kSparseSchur, 2}, {true, LinearSolver::kSparseSchur, 0}}) {
    SCOPED_TRACE(std::string(stereo ? "stereo" : "mono") + ", inverse_depth_points " + std::to_string(inverse_depth));
    const BaScene scene = MakeBaScene(12, 1200, 0.05, stereo, stereo ? 71 : 70);
    const BundleAdjustmentProblem start = Perturbed(scene.truth, 15);
    BundleAdjustmentOptions options = WithSolver(Solver::kSchurLm);
    options.linear_solver = linear_solver;
    options.inverse_depth_points = inverse_depth;
    options.schur_lm_threads = 1;
    BundleAdjustmentProblem one = start;
    const BundleAdjustmentResult r1 = LocalBundleAdjustment(one, options);
    ASSERT_TRUE(r1.success);
    EXPECT_LT(r1.final_rmse_px, 1.05 * scene.noise_rmse_px);
    for (const int threads : {3, 0}) {
      SCOPED_TRACE("schur_lm_threads " + std::to_string(threads));
      options.schur_lm_threads = threads;
      // Four solves side by side, each on its own copy.
      std::vector<BundleAdjustmentProblem> problems(4, start);
      std::vector<BundleAdjustmentResult> results(problems.size());
      tbb::parallel_for(size_t{0}, problems.size(),
                        [&](size_t i) { results[i] = LocalBundleAdjustment(problems[i], options); });
      for (size_t i = 0; i < problems.size(); ++i) {
        ASSERT_TRUE(results[i].success);
        EXPECT_EQ(results[i].iterations, r1.iterations);
        EXPECT_EQ(results[i].outlier, r1.outlier);
        EXPECT_EQ(problems[i].points, one.points);
        for (size_t k = 0; k < one.poses.size(); ++k)
          EXPECT_TRUE(problems[i].poses[k].T_cam_world.matrix() == one.poses[k].T_cam_world.matrix()) << "pose " << k;
      }
    }
  }
}

// The iterative Schur product's kernels against the product written out: for each point,
// -W_j V_j^-1 W_j' p over its observations with a free pose (some observations fixed, some
// points seen twice by one pose), on both vector paths where the CPU has AVX2.
TEST(IterativeSchurProduct, KernelsEqualTheProductWrittenOut) {
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> value(-1, 1);
  const size_t num_poses = 9, num_points = 40;
  std::vector<uint32_t> obs_start = {0};
  std::vector<int> obs_free;
  for (size_t j = 0; j < num_points; ++j) {
    const size_t seen = 1 + rng() % 6;
    for (size_t k = 0; k < seen; ++k) obs_free.push_back(rng() % 5 == 0 ? -1 : static_cast<int>(rng() % num_poses));
    obs_start.push_back(static_cast<uint32_t>(obs_free.size()));
  }
  std::vector<double> W(18 * obs_free.size()), p(6 * num_poses);
  for (double& w : W) w = value(rng);
  for (double& x : p) x = value(rng);
  std::vector<Eigen::Matrix3d> V_inv(num_points);
  for (Eigen::Matrix3d& v : V_inv) {
    const Eigen::Matrix3d A = Eigen::Matrix3d::NullaryExpr([&] { return value(rng); });
    v = A * A.transpose() + Eigen::Matrix3d::Identity();
  }
  Eigen::VectorXd expected = Eigen::VectorXd::Zero(6 * num_poses);
  for (size_t j = 0; j < num_points; ++j) {
    Eigen::Vector3d t = Eigen::Vector3d::Zero();
    for (uint32_t a = obs_start[j]; a < obs_start[j + 1]; ++a)
      if (obs_free[a] >= 0)
        t += Eigen::Map<const Eigen::Matrix<double, 6, 3>>(&W[18 * a]).transpose() *
             Eigen::Map<const Eigen::Matrix<double, 6, 1>>(&p[6 * obs_free[a]]);
    for (uint32_t a = obs_start[j]; a < obs_start[j + 1]; ++a)
      if (obs_free[a] >= 0)
        expected.segment<6>(6 * obs_free[a]) -=
            Eigen::Map<const Eigen::Matrix<double, 6, 3>>(&W[18 * a]) * (V_inv[j] * t);
  }
  auto run = [&](auto kernel) {
    std::vector<double> partial(6 * num_poses, 0.0);
    // Two slices into one buffer: the kernel adds to what is there.
    kernel(obs_start.data(), obs_free.data(), W.data(), V_inv.data(), p.data(), partial.data(), 0, num_points / 3);
    kernel(obs_start.data(), obs_free.data(), W.data(), V_inv.data(), p.data(), partial.data(), num_points / 3,
           num_points);
    return Eigen::VectorXd(Eigen::Map<const Eigen::VectorXd>(partial.data(), partial.size()));
  };
  const Eigen::VectorXd scalar = run(detail::SchurProductSlice);
  EXPECT_GT(expected.norm(), 1.0);
  EXPECT_LT((scalar - expected).norm(), 1e-12 * expected.norm());
#if defined(__x86_64__)
  if (HasAvx2Fma()) {
    const Eigen::VectorXd vector = run(detail::SchurProductSliceAvx2);
    EXPECT_LT((vector - expected).norm(), 1e-12 * expected.norm());
  }
#endif
}

// The reduced camera system's block update against the same product written out in Eigen, to
// the bit: both variants must give the factorizing solver the same system, so that a run's
// result does not depend on whether the CPU has AVX2. Values span many magnitudes, as a local
// adjustment's blocks do, so that a change in the order of the sums shows in the last bits.
TEST(ReducedCameraSystem, BlockUpdateKernelsGiveTheWrittenOutProductsBits) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> mantissa(-1, 1), exponent(-12, 12);
  auto value = [&] { return mantissa(rng) * std::pow(10.0, exponent(rng)); };
  for (int trial = 0; trial < 200; ++trial) {
    Eigen::Matrix<double, 6, 6> S;
    Eigen::Matrix<double, 6, 3> A, B;
    for (double& x : std::span(S.data(), 36)) x = value();
    for (double& x : std::span(A.data(), 18)) x = value();
    for (double& x : std::span(B.data(), 18)) x = value();
    Eigen::Matrix<double, 6, 6> expected = S;
    for (int c = 0; c < 6; ++c)
      for (int r = 0; r < 6; ++r)
        expected(r, c) = S(r, c) - ((A(r, 0) * B(c, 0) + A(r, 1) * B(c, 1)) + A(r, 2) * B(c, 2));
    Eigen::Matrix<double, 6, 6> scalar = S;
    detail::SubtractBlockProduct(scalar.data(), A.data(), B.data());
    EXPECT_EQ(std::memcmp(scalar.data(), expected.data(), sizeof(expected)), 0) << "trial " << trial;
#if defined(__x86_64__)
    if (HasAvx2()) {
      Eigen::Matrix<double, 6, 6> vector = S;
      detail::SubtractBlockProductAvx(vector.data(), A.data(), B.data());
      EXPECT_EQ(std::memcmp(vector.data(), expected.data(), sizeof(expected)), 0) << "trial " << trial;
    }
#endif
  }
}

// The fast path against the reference: both solvers reach the same minimum (same outliers, same
// poses and points to well under the noise), mono and stereo, from the same perturbed start.
TEST(LocalBundleAdjustment, SchurLmMatchesCeres) {
  for (const auto& [stereo, inverse_depth] : {std::pair{false, 0}, {false, 2}, {true, 0}, {true, 1}, {true, 2}}) {
    SCOPED_TRACE("inverse_depth_points " + std::to_string(inverse_depth));
    const BaScene scene = MakeBaScene(12, 1500, 0.05, stereo, stereo ? 51 : 50);
    BundleAdjustmentProblem fast = Perturbed(scene.truth, 12);
    BundleAdjustmentProblem reference = fast;
    BundleAdjustmentOptions options = WithSolver(Solver::kSchurLm);
    options.inverse_depth_points = inverse_depth;
    options.first_pass_iterations = 20;  // run both to convergence
    options.second_pass_iterations = 40;
    const BundleAdjustmentResult rf = LocalBundleAdjustment(fast, options);
    options.solver = Solver::kCeres;
    const BundleAdjustmentResult rr = LocalBundleAdjustment(reference, options);
    ASSERT_TRUE(rf.success && rr.success);
    EXPECT_EQ(rf.outlier, rr.outlier) << (stereo ? "stereo" : "mono");
    EXPECT_NEAR(rf.final_rmse_px, rr.final_rmse_px, 1e-4);
    double max_pose = 0, max_point = 0;
    for (size_t k = 0; k < fast.poses.size(); ++k)
      max_pose = std::max(
          max_pose, (CameraCentre(fast.poses[k].T_cam_world) - CameraCentre(reference.poses[k].T_cam_world)).norm());
    EXPECT_LT(max_pose, 2e-4) << (stereo ? "stereo" : "mono");
    // Points seen in at least two keyframes after outlier removal (one view leaves a mono depth
    // free: each solver's damping settles it differently). Both stop at a relative cost decrease
    // of 1e-6, so weakly constrained points stop at slightly different depths along their rays,
    // where the cost is flattest (millimetres, against their centimetres of error at 5 m): what
    // the observations measure, their projections, must agree to a hundredth of a pixel (the
    // noise is one), and every point to well under its own uncertainty.
    std::vector<int> views(fast.points.size(), 0);
    for (size_t i = 0; i < fast.observations.size(); ++i) views[fast.observations[i].point_index] += !rf.outlier[i];
    auto pixel = [](const BundleAdjustmentProblem& p, const BundleAdjustmentObservation& o) {
      const Eigen::Vector3d x = p.poses[o.pose_index].T_cam_world * p.points[o.point_index];
      return Eigen::Vector2d(p.camera.fx * x.x() / x.z(), p.camera.fy * x.y() / x.z());
    };
    std::vector<double> pixel_differences;
    for (size_t i = 0; i < fast.observations.size(); ++i) {
      const BundleAdjustmentObservation& o = fast.observations[i];
      if (!rf.outlier[i] && views[o.point_index] >= 2)
        pixel_differences.push_back((pixel(fast, o) - pixel(reference, o)).norm());
    }
    std::sort(pixel_differences.begin(), pixel_differences.end());
    EXPECT_LT(pixel_differences[pixel_differences.size() * 99 / 100], 0.01) << (stereo ? "stereo" : "mono");
    for (size_t j = 0; j < fast.points.size(); ++j)
      if (views[j] >= 2) max_point = std::max(max_point, (fast.points[j] - reference.points[j]).norm());
    EXPECT_LT(max_point, 0.05) << (stereo ? "stereo" : "mono");
  }
}

// stop_early ends the solve after the iteration where it first answers true; the partial solution
// is kept and classified, and the refining pass is skipped.
TEST(LocalBundleAdjustment, StopEarlyEndsTheSolveAndKeepsItsProgress) {
  for (Solver solver : {Solver::kSchurLm, Solver::kCeres}) {
    SCOPED_TRACE(solver == Solver::kCeres ? "Ceres" : "Schur LM");
    const BaScene scene = MakeBaScene(8, 600, 0.5, false, 42);
    BundleAdjustmentProblem full = Perturbed(scene.truth, 11);
    BundleAdjustmentProblem stopped = full;
    const BundleAdjustmentResult rf = LocalBundleAdjustment(full, WithSolver(solver));
    BundleAdjustmentOptions options = WithSolver(solver);
    int asked = 0;
    options.stop_early = [&asked] { return ++asked >= 2; };
    const BundleAdjustmentResult rs = LocalBundleAdjustment(stopped, options);
    ASSERT_TRUE(rf.success && rs.success);
    EXPECT_FALSE(rf.stopped_early);
    EXPECT_TRUE(rs.stopped_early);
    EXPECT_LE(rs.iterations, 2);
    EXPECT_GT(rf.iterations, rs.iterations);
    EXPECT_EQ(rs.outlier.size(), stopped.observations.size());
    // Progress made before the stop is kept: the error fell well below its start.
    EXPECT_LT(rs.final_rmse_px, 0.5 * rs.initial_rmse_px);
    EXPECT_LE(rf.final_rmse_px, rs.final_rmse_px);
  }
}

// Points in inverse depth (BundleAdjustmentOptions::inverse_depth_points). A motorway's window:
// keyframes 2.5 m apart driving straight ahead, stereo on a road 5-20 m ahead, and points
// 30-3000 m away seen only monocularly, along nearly parallel rays, each starting 10% off in depth
// (as a far point triangulated from little parallax is). Their depth is all but unobservable: in
// world coordinates the damped steps slide them by kilometres, often behind a camera, and the
// solve runs out of iterations rejecting steps. In inverse depth it converges before its
// iteration caps, to the noise level and to the minimum a solve started from the truth reaches.
TEST(LocalBundleAdjustment, FarMonocularPointsConvergeWithoutSlidingAlongTheirRays) {
  BundleAdjustmentProblem truth;
  truth.camera = TestCamera();
  truth.baseline_m = 0.54;
  const double bf = truth.camera.fx * truth.baseline_m;
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> unit(0, 1);
  std::normal_distribution<double> noise(0, 1);
  const int num_keyframes = 12;
  for (int k = 0; k < num_keyframes; ++k) {
    Eigen::Isometry3d T_world_cam = Eigen::Isometry3d::Identity();
    T_world_cam.translation() = Eigen::Vector3d(0.02 * std::sin(0.5 * k), 0, 2.5 * k);
    truth.poses.push_back({T_world_cam.inverse(), k < 2});
  }
  std::vector<bool> far;
  for (int j = 0; j < 600; ++j) {
    const bool is_far = j % 3 != 0;
    const double z = is_far ? 30 * std::pow(100.0, unit(rng)) : 5 + 2.5 * num_keyframes * unit(rng) + 15 * unit(rng);
    const double x = (unit(rng) - 0.5) * (is_far ? 0.9 * z : 8.0), y = is_far ? -(0.1 + 0.3 * unit(rng)) * z : 1.6;
    truth.points.emplace_back(x, y, z);
    far.push_back(is_far);
  }
  double sum2 = 0;
  int count = 0;
  for (uint32_t j = 0; j < truth.points.size(); ++j) {
    for (uint32_t k = 0; k < truth.poses.size(); ++k) {
      const Eigen::Vector3d xc = truth.poses[k].T_cam_world * truth.points[j];
      if (xc.z() < 3) continue;
      const Eigen::Vector2d px(truth.camera.fx * xc.x() / xc.z() + truth.camera.cx,
                               truth.camera.fy * xc.y() / xc.z() + truth.camera.cy);
      if (px.x() < 0 || px.y() < 0 || px.x() >= truth.camera.width || px.y() >= truth.camera.height) continue;
      BundleAdjustmentObservation o;
      o.pose_index = k;
      o.point_index = j;
      o.uv = px + Eigen::Vector2d(noise(rng), noise(rng));
      if (!far[j] && xc.z() < 20) o.right_u = px.x() - bf / xc.z() + noise(rng);
      truth.observations.push_back(o);
      sum2 += o.right_u >= 0 ? 3 : 2;
      count += o.right_u >= 0 ? 3 : 2;
    }
  }
  const double noise_rmse = std::sqrt(sum2 / count);
  BundleAdjustmentProblem problem = truth;
  for (size_t j = 0; j < problem.points.size(); ++j) {
    const Eigen::Vector3d c = CameraCentre(truth.poses[0].T_cam_world);
    problem.points[j] = c + (far[j] ? (unit(rng) < 0.5 ? 1.1 : 0.9) : 1.0) * (truth.points[j] - c);
  }
  for (size_t k = 2; k < problem.poses.size(); ++k) {
    Eigen::Isometry3d T_world_cam = problem.poses[k].T_cam_world.inverse();
    T_world_cam.translation() += 0.05 * RandomUnit(rng);
    problem.poses[k].T_cam_world = T_world_cam.inverse();
  }
  const BundleAdjustmentProblem start = problem;
  // World coordinates, for the record: the same window runs to its iteration caps.
  BundleAdjustmentProblem world = start;
  const BundleAdjustmentResult rw = LocalBundleAdjustment(world, BundleAdjustmentOptions{});
  std::printf("  world coordinates: %d iterations\n", rw.iterations);
  // The far points have no stereo observation, so both inverse-depth settings cover them.
  for (int inverse_depth : {1, 2}) {
    SCOPED_TRACE("inverse_depth_points " + std::to_string(inverse_depth));
    BundleAdjustmentOptions options;
    options.inverse_depth_points = inverse_depth;
    problem = start;
    const BundleAdjustmentResult r = LocalBundleAdjustment(problem, options);
    ASSERT_TRUE(r.success);
    std::printf("  %d iterations (caps %d + %d), rmse %.3f -> %.3f px, %d outliers\n", r.iterations,
                options.first_pass_iterations, options.second_pass_iterations, r.initial_rmse_px, r.final_rmse_px,
                r.num_outliers);
    EXPECT_LT(r.iterations, options.first_pass_iterations + options.second_pass_iterations);
    EXPECT_LT(r.final_rmse_px, 1.05 * noise_rmse);
    // The minimum the data holds, reached from the truth itself: the perturbed start gets there.
    BundleAdjustmentProblem from_truth = truth;
    ASSERT_TRUE(LocalBundleAdjustment(from_truth, options).success);
    double max_apart = 0;
    for (size_t k = 0; k < problem.poses.size(); ++k)
      max_apart =
          std::max(max_apart,
                   (CameraCentre(problem.poses[k].T_cam_world) - CameraCentre(from_truth.poses[k].T_cam_world)).norm());
    std::printf("  camera centres %.2f mm from the minimum reached from the truth\n", 1e3 * max_apart);
    EXPECT_LT(max_apart, 1e-3);
    // The chi-square gate passes 95% of true observations.
    EXPECT_LT(r.num_outliers, static_cast<int>(0.06 * problem.observations.size()));
  }
}

TEST(LocalBundleAdjustment, NoiseFreeIsExact) {
  for (Solver solver : {Solver::kSchurLm, Solver::kCeres}) {
    SCOPED_TRACE(solver == Solver::kCeres ? "Ceres" : "Schur LM");
    BaScene scene = MakeBaScene(5, 200, 0.0, true, 41);
    // Re-project without noise.
    const BundleAdjustmentProblem& t = scene.truth;
    const double bf = t.camera.fx * t.baseline_m;
    for (BundleAdjustmentObservation& obs : scene.truth.observations) {
      const Eigen::Vector3d x = t.poses[obs.pose_index].T_cam_world * t.points[obs.point_index];
      obs.uv = Eigen::Vector2d(t.camera.fx * x.x() / x.z() + t.camera.cx, t.camera.fy * x.y() / x.z() + t.camera.cy);
      if (obs.right_u >= 0) obs.right_u = obs.uv.x() - bf / x.z();
    }
    BundleAdjustmentProblem problem = Perturbed(scene.truth, 10);
    const BundleAdjustmentResult r = LocalBundleAdjustment(problem, WithSolver(solver));
    ASSERT_TRUE(r.success);
    EXPECT_EQ(r.num_outliers, 0);
    EXPECT_LT(r.final_rmse_px, 1e-4);
    for (size_t k = 0; k < problem.poses.size(); ++k)
      EXPECT_LT((CameraCentre(problem.poses[k].T_cam_world) - CameraCentre(t.poses[k].T_cam_world)).norm(), 1e-5);
  }
}

TEST(LocalBundleAdjustment, RejectsMisuse) {
  BaScene scene = MakeBaScene(3, 20, 0.0, false, 42);
  BundleAdjustmentProblem p = scene.truth;
  p.observations[0].point_index = 1000;
  EXPECT_THROW((void)LocalBundleAdjustment(p, BundleAdjustmentOptions{}), Error);
  p = scene.truth;
  p.observations[0].pose_index = 7;
  EXPECT_THROW((void)LocalBundleAdjustment(p, BundleAdjustmentOptions{}), Error);
  p = scene.truth;
  p.observations[0].right_u = 100;
  p.baseline_m = 0;
  EXPECT_THROW((void)LocalBundleAdjustment(p, BundleAdjustmentOptions{}), Error);
  BundleAdjustmentOptions bad;
  bad.num_threads = 0;
  EXPECT_FALSE(bad.Check());
  p = scene.truth;
  EXPECT_THROW((void)LocalBundleAdjustment(p, bad), Error);
}

}  // namespace
}  // namespace flatslam
