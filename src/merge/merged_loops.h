// Loop closing in a merged map. A merge joins maps where they overlap (its seams); where agents
// met again elsewhere, after drifting apart, or where an agent's own loop went unnoticed, the
// merged map still holds the drift between. CloseLoopsInMergedMap replays the map's keyframes,
// agent by agent in creation order, through the session's loop detection against the keyframes
// replayed before (bag-of-words candidates that are not covisible, temporal consistency,
// geometric verification), and corrects each verified loop as a session does (CorrectLoop: the
// keyframe and its neighbours moved by the loop's transform, points fused, the essential graph
// optimized with the matched keyframe held).
// Concurrency: writes the map (exclusive access), on the caller's thread.
#pragma once

#include <cstdint>
#include <vector>

#include "config/context.h"
#include "ecs/map.h"
#include "place/loop_closing.h"
#include "place/vocabulary.h"

namespace flatslam {

struct MergedMapLoops {
  std::vector<LoopClosure> closures;  // in the order they were closed
  size_t keyframes = 0;               // replayed
  double ms = 0;
};

// Keyframes without a bag of words get one. `seed` seeds the verification's RANSAC.
MergedMapLoops CloseLoopsInMergedMap(Map& map, const Vocabulary& vocabulary, const SystemContext& context,
                                     uint64_t seed = 2);

}  // namespace flatslam
