#include "merge/merged_loops.h"

#include <algorithm>
#include <chrono>
#include <tuple>

#include "mapping/map_bundle_adjustment.h"
#include "merge/map_merge.h"

namespace flatslam {

void MergedMapLoopCloser::Replay(Map& map, std::span<const KeyFrameHandle> keyframes, const SystemContext& context,
                                 bool adjust, MergedMapLoops* out) {
  const auto start = std::chrono::steady_clock::now();
  const size_t closures_before = out->closures.size();
  for (KeyFrameHandle h : keyframes) {
    if (!map.keyframes().contains(h)) continue;
    if (const uint32_t agent = map.keyframe(h).agent; agent != agent_) {
      groups_[agent_] = std::move(state_.consistent_groups);
      state_.consistent_groups = std::move(groups_[agent]);
      agent_ = agent;
    }
    ++out->keyframes;
    const size_t closed = state_.closures.size();
    if (const auto loop = DetectLoop(map, database_, state_, context, h, true))
      CorrectLoop(map, state_, context, h, *loop);
    out->closures.insert(out->closures.end(), state_.closures.begin() + static_cast<std::ptrdiff_t>(closed),
                         state_.closures.end());
  }
  if (adjust && out->closures.size() > closures_before) {
    const auto gba_start = std::chrono::steady_clock::now();
    // The gauge: the lowest agent's first keyframe, the first in replay order.
    const std::vector<KeyFrameHandle> order = ReplayOrder(map, map.keyframes().handles());
    MapBundleAdjustment ba;
    if (!order.empty() && BuildGlobalBundleAdjustment(map, context, order.front(), &ba)) {
      const BundleAdjustmentResult result = SolveGlobalBundleAdjustment(ba, context, [] { return false; });
      if (result.success) {
        ApplyGlobalBundleAdjustment(map, context, ba, result);
        ++out->global_adjustments;
      }
    }
    out->global_adjustment_ms +=
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - gba_start).count();
  }
  out->ms += std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

std::vector<KeyFrameHandle> ReplayOrder(const Map& map, std::span<const KeyFrameHandle> keyframes) {
  std::vector<KeyFrameHandle> order(keyframes.begin(), keyframes.end());
  std::sort(order.begin(), order.end(), [&](KeyFrameHandle a, KeyFrameHandle b) {
    const KeyFrame &ka = map.keyframe(a), &kb = map.keyframe(b);
    return std::tie(ka.agent, ka.id) < std::tie(kb.agent, kb.id);
  });
  return order;
}

MergedMapLoops CloseLoopsInMergedMap(Map& map, const Vocabulary& vocabulary, const SystemContext& context,
                                     uint64_t seed, MergedMapLoopCloser* closer, bool adjust) {
  ComputeKeyFrameBow(map, vocabulary, true);
  MergedMapLoopCloser replay(vocabulary, seed);
  MergedMapLoops out;
  replay.Replay(map, ReplayOrder(map, map.keyframes().handles()), context, adjust, &out);
  if (closer) *closer = std::move(replay);
  return out;
}

}  // namespace flatslam
