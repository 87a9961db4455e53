// The map server applying agents' keyframe messages (AgentMaps::Add) and bringing the points'
// statistics up to date before a merge (AgentMaps::RefreshPointStats), on a map the size of two
// joined town sessions: 576 keyframes x 1,200 keypoints, 28,000 points seen by 8 keyframes each.
// "Updates" applies every keyframe a second time, as an agent's final map update does. Times are
// for all 576 messages.
// Run: bench_agent_maps [--benchmark_filter=...] [--benchmark_repetitions=N]
#include <vector>

#include <benchmark/benchmark.h>

#include "merge/agent_maps.h"
#include "storage/keyframe_message.h"
#include "storage/random_map.h"

namespace flatslam {
namespace {

const std::vector<std::vector<uint8_t>>& Messages() {
  static const std::vector<std::vector<uint8_t>> messages = [] {
    testing::RandomMapOptions o;
    o.keyframes = 576;
    o.keypoints = 1200;
    o.points = 28000;
    o.observations_per_point = 8;
    o.agents = 1;
    o.erase_some = false;
    const Map map = testing::RandomMap(o);
    std::vector<std::vector<uint8_t>> out;
    for (KeyFrameHandle h : map.keyframes().handles())
      out.push_back(EncodeKeyFrameMessage(map, h, 0, 1, testing::TestAgentCamera()));
    return out;
  }();
  return messages;
}

void ApplyAll(AgentMaps* maps) {
  for (const std::vector<uint8_t>& m : Messages()) maps->Add(DecodeKeyFrameMessage(m, "message"));
}

void BM_NewKeyFrames(benchmark::State& state) {
  for (auto _ : state) {
    AgentMaps maps;
    ApplyAll(&maps);
    benchmark::DoNotOptimize(maps.sessions().size());
  }
}
BENCHMARK(BM_NewKeyFrames)->Unit(benchmark::kMillisecond);

void BM_Updates(benchmark::State& state) {
  AgentMaps maps;
  ApplyAll(&maps);
  maps.RefreshPointStats();
  for (auto _ : state) ApplyAll(&maps);
}
BENCHMARK(BM_Updates)->Unit(benchmark::kMillisecond);

void BM_RefreshPointStats(benchmark::State& state) {
  AgentMaps maps;
  ApplyAll(&maps);
  for (auto _ : state) {
    state.PauseTiming();
    ApplyAll(&maps);  // every point named again
    state.ResumeTiming();
    maps.RefreshPointStats();
  }
}
BENCHMARK(BM_RefreshPointStats)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace flatslam

BENCHMARK_MAIN();
