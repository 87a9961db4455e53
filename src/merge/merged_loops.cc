#include "merge/merged_loops.h"

#include <algorithm>
#include <chrono>
#include <tuple>
#include <unordered_set>

#include "core/clock.h"
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
    // The agents whose loops closed are free; every other agent's keyframes hold, as they held in
    // the loops' corrections: freed, a held agent was bent by the drift being corrected
    // (docs/STATUS.md, "Map merge"). With no agent held, the gauge is the lowest agent's first
    // keyframe, the first in replay order.
    std::unordered_set<uint32_t> looped;
    for (size_t c = closures_before; c < out->closures.size(); ++c) looped.insert(out->closures[c].agent);
    const std::vector<KeyFrameHandle> order = ReplayOrder(map, map.keyframes().handles());
    std::vector<KeyFrameHandle> free;
    for (KeyFrameHandle h : order)
      if (looped.count(map.keyframe(h).agent)) free.push_back(h);
    MapBundleAdjustment ba;
    BuildMapBundleAdjustment(map, context.geometry, context.stereo_depth, free,
                             free.size() == order.size() ? order.front() : KeyFrameHandle(), 2, &ba);
    // Free keyframes that see no point of a held one have no gauge: the first of them (the build
    // puts `free` first, in order) holds.
    std::vector<BundleAdjustmentPose>& poses = ba.problem.poses;
    if (!poses.empty() && std::none_of(poses.begin(), poses.end(), [](const auto& p) { return p.fixed; }))
      poses.front().fixed = true;
    if (!ba.problem.observations.empty()) {
      const BundleAdjustmentResult result = SolveGlobalBundleAdjustment(ba, context, [] { return false; });
      if (result.success) {
        ApplyGlobalBundleAdjustment(map, context, ba, result);
        ++out->global_adjustments;
      }
    }
    out->global_adjustment_ms += MsSince(gba_start);
  }
  out->ms += MsSince(start);
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
