// Local bundle adjustment on a window shaped like the motorway's (synth:highway): 21 free
// keyframes 2.5 m apart and the fixed keyframes that share their points, 3,200 points (a third on
// the road within 30 m with stereo observations, the rest 30-3000 m away), each seen by 6-18
// consecutive keyframes: about 37,000 observations. Arguments: schur_lm_threads (1: the calling
// thread only; 0: every core). The results of both are the same bits (tested in
// tests/optimization/bundle_adjustment_test.cc); this measures what the threads buy.
#include <cmath>
#include <random>

#include <benchmark/benchmark.h>

#include "optimization/bundle_adjustment.h"

namespace flatslam {
namespace {

BundleAdjustmentProblem MotorwayWindow() {
  BundleAdjustmentProblem p;
  p.camera.fx = p.camera.fy = 718;
  p.camera.cx = 620;
  p.camera.cy = 188;
  p.camera.width = 1241;
  p.camera.height = 376;
  p.baseline_m = 0.54;
  const double bf = p.camera.fx * p.baseline_m;
  constexpr int kKeyFrames = 60, kFree = 21, kPoints = 3200;
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> unit(0, 1);
  std::normal_distribution<double> noise(0, 1);
  std::vector<Eigen::Isometry3d> truth;
  for (int k = 0; k < kKeyFrames; ++k) {
    Eigen::Isometry3d T_world_cam = Eigen::Isometry3d::Identity();
    T_world_cam.translation() = Eigen::Vector3d(0.3 * std::sin(0.05 * k), 0, 2.5 * k);
    truth.push_back(T_world_cam.inverse());
    Eigen::Isometry3d start = T_world_cam;
    if (k >= kKeyFrames - kFree) start.translation() += 0.05 * Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    p.poses.push_back({start.inverse(), k < kKeyFrames - kFree});
  }
  for (int j = 0; j < kPoints; ++j) {
    const bool near = j % 3 == 0;
    const int span = 6 + static_cast<int>(12 * unit(rng));
    const int last = kKeyFrames - 1 - static_cast<int>((kFree - 1) * unit(rng));
    const int first = std::max(0, last - span + 1);
    // Placed ahead of the span's first keyframe, where all of it sees the point in front.
    const double ahead = near ? 2.5 * span + 5 + 20 * unit(rng) : 30 * std::pow(100.0, unit(rng));
    const double z = 2.5 * first + ahead;
    const double x = (unit(rng) - 0.5) * (near ? 8.0 : 0.8 * ahead);
    const double y = near ? 1.6 : -(0.05 + 0.3 * unit(rng)) * ahead;
    const Eigen::Vector3d X(x, y, z);
    p.points.push_back(X + (near ? 0.02 : 0.05 * ahead / 30) * Eigen::Vector3d(noise(rng), noise(rng), noise(rng)));
    for (int k = first; k <= last; ++k) {
      const Eigen::Vector3d xc = truth[k] * X;
      if (xc.z() < 1) continue;
      BundleAdjustmentObservation o;
      o.pose_index = static_cast<uint32_t>(k);
      o.point_index = static_cast<uint32_t>(j);
      o.uv = Eigen::Vector2d(p.camera.fx * xc.x() / xc.z() + p.camera.cx + noise(rng),
                             p.camera.fy * xc.y() / xc.z() + p.camera.cy + noise(rng));
      if (near && xc.z() < 35 * p.baseline_m) o.right_u = o.uv.x() - bf / xc.z() + noise(rng);
      p.observations.push_back(o);
    }
  }
  return p;
}

void BM_LocalBundleAdjustmentMotorwayWindow(benchmark::State& state) {
  const BundleAdjustmentProblem start = MotorwayWindow();
  BundleAdjustmentOptions options;
  options.schur_lm_threads = static_cast<int>(state.range(0));
  BundleAdjustmentWorkspace workspace;
  int iterations = 0;
  for (auto _ : state) {
    state.PauseTiming();
    BundleAdjustmentProblem problem = start;
    state.ResumeTiming();
    const BundleAdjustmentResult r = LocalBundleAdjustment(problem, options, &workspace);
    iterations = r.iterations;
    benchmark::DoNotOptimize(problem.points.data());
  }
  state.counters["observations"] = static_cast<double>(start.observations.size());
  state.counters["solver_iterations"] = iterations;
}
BENCHMARK(BM_LocalBundleAdjustmentMotorwayWindow)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace flatslam

BENCHMARK_MAIN();
