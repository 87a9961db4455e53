// Vocabulary timings on a 1e6-word tree (branching 10, 6 levels, full; node descriptors random,
// built once into a temporary file): load (mmap + verification) on one thread and on all cores, one descriptor to its
// word on one thread, and a 2000-descriptor frame to its bag of words on one thread and on all cores.
#include <benchmark/benchmark.h>
#include <tbb/task_arena.h>
#include <unistd.h>

#include <cstdint>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "io/dataset.h"
#include "frontend/orb_extractor.h"
#include "place/vocabulary.h"

namespace {

constexpr int kBranching = 10;
constexpr int kLevels = 6;

// The benchmark vocabulary file, written on first use and removed at exit.
class BigVocabulary {
 public:
  static const BigVocabulary& Get() {
    static const BigVocabulary instance;
    return instance;
  }
  const std::filesystem::path& path() const { return path_; }
  const flatslam::Vocabulary& vocabulary() const { return vocabulary_; }

 private:
  BigVocabulary() {
    const size_t nodes = flatslam::Vocabulary::node_count_for(kBranching, kLevels);
    std::mt19937_64 rng(42);
    std::vector<flatslam::Descriptor> descriptors(nodes);
    for (auto& d : descriptors) d = {rng(), rng(), rng(), rng()};
    std::vector<uint8_t> children(nodes, 0);
    const size_t inner = flatslam::Vocabulary::node_count_for(kBranching, kLevels - 1);
    for (size_t i = 0; i < inner; ++i) children[i] = kBranching;
    std::vector<float> weights(nodes - inner);
    for (auto& w : weights) w = 0.1f + static_cast<float>(rng() % 1000) / 100.f;
    path_ = std::filesystem::temp_directory_path() / ("flatslam_bench_vocab_" + std::to_string(::getpid()) + ".fsvc");
    flatslam::Vocabulary::FromNodes(kBranching, kLevels, descriptors, children, weights).Save(path_);
    vocabulary_ = flatslam::Vocabulary::Load(path_);
  }
  ~BigVocabulary() { std::filesystem::remove(path_); }

  std::filesystem::path path_;
  flatslam::Vocabulary vocabulary_;
};

// Descriptors near the tree's leaves (so descents are not all alike), as queries.
std::vector<flatslam::Descriptor> Queries(const flatslam::Vocabulary& v, size_t count, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::vector<flatslam::Descriptor> out(count);
  const size_t inner = flatslam::Vocabulary::node_count_for(kBranching, kLevels - 1);
  for (auto& d : out) {
    d = v.node_descriptor(static_cast<uint32_t>(inner + rng() % (v.node_count() - inner)));
    for (int flip = 0; flip < 20; ++flip) {
      const int bit = static_cast<int>(rng() % 256);
      d[bit / 64] ^= uint64_t{1} << (bit % 64);
    }
  }
  return out;
}

// range(0): threads for the checksum (0 = the default arena, all cores).
void BM_Load(benchmark::State& state) {
  const BigVocabulary& big = BigVocabulary::Get();
  auto body = [&] {
    for (auto _ : state) {
      const flatslam::Vocabulary v = flatslam::Vocabulary::Load(big.path());
      benchmark::DoNotOptimize(v.word_count());
    }
  };
  const int threads = static_cast<int>(state.range(0));
  if (threads == 0) {
    body();
  } else {
    tbb::task_arena(threads).execute(body);
  }
  state.counters["words"] = static_cast<double>(big.vocabulary().word_count());
  state.counters["MiB"] = static_cast<double>(big.vocabulary().byte_size()) / 1048576.0;
}
BENCHMARK(BM_Load)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

void BM_TransformDescriptor(benchmark::State& state) {
  const flatslam::Vocabulary& v = BigVocabulary::Get().vocabulary();
  const std::vector<flatslam::Descriptor> queries = Queries(v, 1 << 16, 7);
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(v.Transform(queries[i++ & (queries.size() - 1)]));
  }
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()));
}
BENCHMARK(BM_TransformDescriptor)->Unit(benchmark::kNanosecond);

// range(0): threads (0 = the default arena, all cores).
void BM_TransformFrame(benchmark::State& state) {
  const flatslam::Vocabulary& v = BigVocabulary::Get().vocabulary();
  std::vector<std::vector<flatslam::Descriptor>> frames;
  for (uint64_t f = 0; f < 16; ++f) frames.push_back(Queries(v, 2000, 100 + f));
  flatslam::BowVector bow;
  flatslam::FeatureVector features;
  size_t i = 0;
  auto body = [&] {
    for (auto _ : state) {
      v.Transform(frames[i++ % frames.size()], &bow, &features, 4);
      benchmark::DoNotOptimize(bow.data());
    }
  };
  const int threads = static_cast<int>(state.range(0));
  if (threads == 0) {
    body();
  } else {
    tbb::task_arena(threads).execute(body);
  }
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()) * 2000);
}
BENCHMARK(BM_TransformFrame)->Arg(1)->Arg(0)->Unit(benchmark::kMillisecond);

// The shipped vocabulary (100k words) on ORB descriptors of rendered frames, per descriptor on
// one thread.
void BM_TransformDefaultDescriptor(benchmark::State& state) {
  const flatslam::Vocabulary v = flatslam::Vocabulary::Load(flatslam::DefaultVocabularyPath());
  const auto dataset = flatslam::OpenDataset("synth:town:sensor=mono,fps=1");
  const flatslam::OrbExtractor orb;
  std::vector<flatslam::Descriptor> queries;
  for (size_t i = 0; i < dataset->size(); i += 10) {
    flatslam::Keypoints keypoints;
    orb.Extract(dataset->read(i).left, &keypoints);
    queries.insert(queries.end(), keypoints.descriptor.begin(), keypoints.descriptor.end());
  }
  size_t i = 0;
  for (auto _ : state) benchmark::DoNotOptimize(v.Transform(queries[i++ % queries.size()]));
  state.counters["words"] = static_cast<double>(v.word_count());
  state.SetItemsProcessed(static_cast<int64_t>(state.iterations()));
}
BENCHMARK(BM_TransformDefaultDescriptor)->Unit(benchmark::kNanosecond);

}  // namespace

BENCHMARK_MAIN();
