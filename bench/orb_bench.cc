// ORB extraction and stereo matching time: KITTI 07 (1226x370, 2000 features) on one thread and
// on the default TBB arena, synthetic 640x480 (1000 features), KITTI 06 stereo pairs.
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include <benchmark/benchmark.h>
#include <opencv2/core.hpp>
#include <tbb/parallel_invoke.h>
#include <tbb/task_arena.h>

#include "io/image_io.h"
#include "io/synthetic.h"
#include "frontend/orb_extractor.h"
#include "frontend/stereo_matcher.h"

namespace {

std::filesystem::path DatasetsDir() {
  if (const char* env = std::getenv("FLATSLAM_DATASETS_DIR")) return env;
  return std::filesystem::path(__FILE__).parent_path() / "../../shared/datasets";
}

flatslam::OrbExtractor MakeExtractor(int features, bool use_avx2 = true) {
  flatslam::OrbOptions options;
  options.features = features;
  options.use_avx2 = use_avx2;
  return flatslam::OrbExtractor(options);
}

// threads 0 = the default arena; OpenCV's own pool is limited alike so "1" really is one core.
void RunIn(int threads, const std::function<void()>& body) {
  cv::setNumThreads(threads == 0 ? -1 : threads);
  if (threads == 0) {
    body();
  } else {
    tbb::task_arena(threads).execute(body);
  }
}

// range(0): threads (0 = default arena); range(1): 1 = AVX2 kernels where available, 0 = baseline.
void BM_ExtractKitti(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  std::vector<cv::Mat> images;
  for (int i = 0; i < 10; ++i) {
    char name[32];
    std::snprintf(name, sizeof(name), "%06d.png", i * 15);
    images.push_back(flatslam::ReadGrayImage(DatasetsDir() / "kitti/sequences/07/image_0" / name));
  }
  const flatslam::OrbExtractor orb = MakeExtractor(2000, state.range(1) != 0);
  flatslam::Keypoints kps;
  flatslam::ImagePyramid pyramid;  // reused, as a pipeline stage would
  size_t i = 0, total = 0;
  RunIn(threads, [&] {
    for (auto _ : state) {
      orb.Extract(images[i++ % images.size()], &kps, &pyramid);
      total += kps.size();
    }
  });
  state.counters["keypoints"] = static_cast<double>(total) / state.iterations();
}
BENCHMARK(BM_ExtractKitti)
    ->Args({1, 1})
    ->Args({0, 1})
    ->Args({1, 0})
    ->ArgNames({"threads", "avx2"})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

void BM_ExtractSynthetic(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  flatslam::SyntheticOptions options;
  options.sensor = flatslam::Sensor::kMonocular;
  flatslam::SyntheticScene scene(flatslam::MakeScene("room"), options);
  std::vector<cv::Mat> images;
  for (size_t f = 0; f < 10; ++f) images.push_back(scene.Render(f * 20).left);
  const flatslam::OrbExtractor orb = MakeExtractor(1000);
  flatslam::Keypoints kps;
  size_t i = 0, total = 0;
  RunIn(threads, [&] {
    for (auto _ : state) {
      orb.Extract(images[i++ % images.size()], &kps);
      total += kps.size();
    }
  });
  state.counters["keypoints"] = static_cast<double>(total) / state.iterations();
}
BENCHMARK(BM_ExtractSynthetic)->Arg(1)->Arg(0)->ArgName("threads")->Unit(benchmark::kMillisecond)->UseRealTime();

// Matching only (both images extracted beforehand).
void BM_StereoMatchKitti(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  const flatslam::OrbExtractor orb = MakeExtractor(2000);
  struct Pair {
    flatslam::Keypoints left, right;
    flatslam::ImagePyramid left_pyramid, right_pyramid;
  };
  std::vector<Pair> pairs(5);
  for (size_t k = 0; k < pairs.size(); ++k) {
    char name[32];
    std::snprintf(name, sizeof(name), "%06zu.png", k * 10);
    orb.Extract(flatslam::ReadGrayImage(DatasetsDir() / "kitti/sequences/06/image_0" / name), &pairs[k].left,
                &pairs[k].left_pyramid);
    orb.Extract(flatslam::ReadGrayImage(DatasetsDir() / "kitti/sequences/06/image_1" / name), &pairs[k].right,
                &pairs[k].right_pyramid);
  }
  const flatslam::StereoOptions options;
  size_t i = 0, matched = 0;
  RunIn(threads, [&] {
    for (auto _ : state) {
      Pair& p = pairs[i++ % pairs.size()];
      matched += flatslam::MatchStereo(p.right, p.left_pyramid, p.right_pyramid, orb.scales(), 707.0912, 0.537, options,
                                       &p.left)
                     .matched;
    }
  });
  state.counters["matched"] = static_cast<double>(matched) / state.iterations();
}
BENCHMARK(BM_StereoMatchKitti)->Arg(1)->Arg(0)->ArgName("threads")->Unit(benchmark::kMillisecond)->UseRealTime();

// A whole stereo frame: both extractions (as two tasks) and the matching.
void BM_StereoFrameKitti(benchmark::State& state) {
  const int threads = static_cast<int>(state.range(0));
  const flatslam::OrbExtractor orb = MakeExtractor(2000);
  const cv::Mat left = flatslam::ReadGrayImage(DatasetsDir() / "kitti/sequences/06/image_0/000000.png");
  const cv::Mat right = flatslam::ReadGrayImage(DatasetsDir() / "kitti/sequences/06/image_1/000000.png");
  flatslam::Keypoints kl, kr;
  flatslam::ImagePyramid pl, pr;
  RunIn(threads, [&] {
    for (auto _ : state) {
      tbb::parallel_invoke([&] { orb.Extract(left, &kl, &pl); }, [&] { orb.Extract(right, &kr, &pr); });
      benchmark::DoNotOptimize(
          flatslam::MatchStereo(kr, pl, pr, orb.scales(), 707.0912, 0.537, flatslam::StereoOptions(), &kl));
    }
  });
}
BENCHMARK(BM_StereoFrameKitti)->Arg(1)->Arg(0)->ArgName("threads")->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
