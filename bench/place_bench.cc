// Keyframe database query time as the database grows to 10,000 keyframes, with the shipped
// vocabulary: bags of words come from ORB descriptors of synthetic town frames (three agents),
// each database keyframe a frame's bag with a random 30% of its words dropped (revisits differ).
#include <algorithm>
#include <cstdio>
#include <random>
#include <vector>

#include <benchmark/benchmark.h>

#include "io/dataset.h"
#include "place/keyframe_database.h"
#include "frontend/orb_extractor.h"
#include "place/vocabulary.h"

namespace {

using namespace flatslam;

struct Fixture {
  Vocabulary vocabulary = Vocabulary::Load(DefaultVocabularyPath());
  std::vector<BowVector> frames;  // one bag per rendered frame

  Fixture() {
    OrbExtractor orb(OrbOptions{});
    for (int agent = 0; agent < 3; ++agent) {
      DatasetOptions options;
      const auto dataset = OpenDataset("synth:town:width=480,height=360,agent=" + std::to_string(agent), options);
      for (size_t i = 0; i < dataset->size(); i += 8) {
        Keypoints kps;
        orb.Extract(dataset->read(i).left, &kps);
        BowVector bow;
        vocabulary.Transform(kps.descriptor, &bow, nullptr);
        frames.push_back(std::move(bow));
      }
    }
  }
};

Fixture& Shared() {
  static Fixture fixture;
  return fixture;
}

BowVector Thinned(const BowVector& bow, std::mt19937_64& rng) {
  std::bernoulli_distribution keep(0.7);
  BowVector out;
  float sum = 0;
  for (const auto& e : bow)
    if (keep(rng)) out.push_back(e), sum += e.second;
  for (auto& e : out) e.second /= sum;
  return out;
}

// range(0): keyframes in the database.
void BM_RelocalizationQuery(benchmark::State& state) {
  Fixture& f = Shared();
  const size_t n = static_cast<size_t>(state.range(0));
  std::mt19937_64 rng(1);
  Map map;
  KeyFrameDatabase db(f.vocabulary.word_count());
  for (size_t k = 0; k < n; ++k) {
    KeyFrame kf;
    kf.bow = Thinned(f.frames[k % f.frames.size()], rng);
    const BowVector bow = kf.bow;
    db.Add(map.AddKeyFrame(std::move(kf)), bow);
  }
  size_t q = 0, candidates = 0;
  for (auto _ : state) {
    const auto c = db.DetectRelocalizationCandidates(map, f.frames[(q++ * 7) % f.frames.size()]);
    candidates += c.size();
    benchmark::DoNotOptimize(c.data());
  }
  state.counters["frames_rendered"] = static_cast<double>(f.frames.size());
  state.counters["candidates"] = static_cast<double>(candidates) / static_cast<double>(state.iterations());
}
BENCHMARK(BM_RelocalizationQuery)->Arg(100)->Arg(1000)->Arg(10000)->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
