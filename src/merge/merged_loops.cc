#include "merge/merged_loops.h"

#include <algorithm>
#include <chrono>
#include <tuple>

#include "merge/map_merge.h"

namespace flatslam {

MergedMapLoops CloseLoopsInMergedMap(Map& map, const Vocabulary& vocabulary, const SystemContext& context,
                                     uint64_t seed) {
  const auto start = std::chrono::steady_clock::now();
  ComputeKeyFrameBow(map, vocabulary, true);
  // Agent by agent, each in the order its keyframes were made: temporal consistency needs a
  // run's consecutive keyframes, and each agent's keyframes then meet every earlier agent's.
  const auto handles = map.keyframes().handles();
  std::vector<KeyFrameHandle> order(handles.begin(), handles.end());
  std::sort(order.begin(), order.end(), [&](KeyFrameHandle a, KeyFrameHandle b) {
    const KeyFrame &ka = map.keyframe(a), &kb = map.keyframe(b);
    return std::tie(ka.agent, ka.id) < std::tie(kb.agent, kb.id);
  });
  KeyFrameDatabase database(vocabulary.word_count());
  LoopClosingState state(seed);
  MergedMapLoops out;
  uint32_t agent = order.empty() ? 0 : map.keyframe(order.front()).agent;
  for (KeyFrameHandle h : order) {
    if (!map.keyframes().contains(h)) continue;
    // A new agent's first keyframes continue no consistent group of the previous agent's.
    if (map.keyframe(h).agent != agent) {
      agent = map.keyframe(h).agent;
      state.consistent_groups.clear();
    }
    ++out.keyframes;
    if (const auto loop = DetectLoop(map, database, state, context, h, true))
      CorrectLoop(map, state, context, h, *loop);
  }
  out.closures = state.closures;
  out.ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
  return out;
}

}  // namespace flatslam
