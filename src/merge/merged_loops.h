// Loop closing in a merged map. A merge joins maps where they overlap (its seams); where agents met
// again elsewhere, after drifting apart, or where an agent's own loop went unnoticed, the merged
// map still holds the drift between. CloseLoopsInMergedMap replays the map's keyframes, agent by
// agent in creation order, through the session's loop detection against the keyframes replayed
// before (bag-of-words candidates that are not covisible, temporal consistency, geometric
// verification), and corrects each verified loop as a session does (CorrectLoop: the keyframe and
// its neighbours moved by the loop's transform, points fused, the essential graph optimized with
// the matched keyframe held), moving only the loop's agent (every other agent's keyframes hold,
// as a merge holds the map merged into), then, as a session does after its loops (unless the caller
// leaves it out), adjusts the loops' agents: a bundle adjustment of every keyframe of theirs and every
// point they see, the other agents' keyframes held (with no other agent, the lowest agent's first
// keyframe holds; when the free keyframes see no point of a held one, their first). The essential
// graph spreads a loop's correction over the poses; the adjustment puts the points and the shape along
// the loop back in agreement with every observation. A MergedMapLoopCloser keeps what the replay built
// (keyframe database, each agent's consistent groups), so that keyframes added to the map later
// continue it (merge/live_merge.h).
// Concurrency: writes the map (exclusive access), on the caller's thread; a closer is used by one
// caller at a time.
#pragma once

#include <cstdint>
#include <map>
#include <span>
#include <vector>

#include "config/context.h"
#include "ecs/map.h"
#include "place/keyframe_database.h"
#include "place/loop_closing.h"
#include "place/vocabulary.h"

namespace flatslam {

struct MergedMapLoops {
  std::vector<LoopClosure> closures;  // in the order they were closed
  size_t keyframes = 0;               // replayed
  double ms = 0;                      // all of it, global bundle adjustments included
  size_t global_adjustments = 0;      // one after each replay that closed a loop (of the loops' agents)
  double global_adjustment_ms = 0;
};

class MergedMapLoopCloser {
 public:
  MergedMapLoopCloser(const Vocabulary& vocabulary, uint64_t seed) : database_(vocabulary.word_count()), state_(seed) {
    state_.hold_other_agents = true;
  }
  // Replays `keyframes` of `map` (each with its bag of words), in the order given, after those of
  // earlier calls; each agent's keyframes continue its own consistent groups (temporal
  // consistency needs a run's consecutive keyframes); when a loop closed and `adjust`, one global
  // bundle adjustment follows the replay. Adds to *out.
  void Replay(Map& map, std::span<const KeyFrameHandle> keyframes, const SystemContext& context, bool adjust,
              MergedMapLoops* out);

 private:
  KeyFrameDatabase database_;
  LoopClosingState state_;
  uint32_t agent_ = 0;                                                         // whose consistent groups state_ holds
  std::map<uint32_t, std::vector<LoopClosingState::ConsistentGroup>> groups_;  // the other agents'
};

// The keyframes of `map` in replay order: agent by agent, each in the order its keyframes were
// made (each agent's keyframes then meet every earlier agent's).
[[nodiscard]] std::vector<KeyFrameHandle> ReplayOrder(const Map& map, std::span<const KeyFrameHandle> keyframes);

// Every keyframe of `map` replayed through a new closer (adjusted after loops if `adjust`),
// returned in *closer when given.
// Keyframes without a bag of words get one. `seed` seeds the verification's RANSAC.
MergedMapLoops CloseLoopsInMergedMap(Map& map, const Vocabulary& vocabulary, const SystemContext& context,
                                     uint64_t seed = 2, MergedMapLoopCloser* closer = nullptr, bool adjust = true);

}  // namespace flatslam
