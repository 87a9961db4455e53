// Loop closing: each keyframe local mapping finished is indexed in the place index and searched
// for a loop (bag-of-words candidates, temporal consistency over loop_consistency keyframes,
// geometric verification); a verified loop is corrected (the keyframe and its neighbours moved
// by the loop's Sim(3)/SE(3), points fused across the loop, the essential graph optimized), and
// global bundle adjustment may refine the whole map afterwards.
// Concurrency: DetectLoop writes the keyframe database and reads the map; CorrectLoop and
// ApplyGlobalBundleAdjustment write the map (exclusive access); BuildGlobalBundleAdjustment reads
// it; the global solve in between touches no map. A LoopClosingState is used by one caller at a
// time (the session's place node).
#pragma once

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <random>
#include <vector>

#include "config/context.h"
#include "ecs/map.h"
#include "mapping/map_bundle_adjustment.h"
#include "place/keyframe_database.h"
#include "place/place_verification.h"

namespace flatslam {

// One loop closure, for the run summary and tests.
struct LoopClosure {
  size_t frame_index = 0;                 // input frame of the keyframe that closed the loop
  size_t matched_frame_index = 0;         // input frame of the keyframe it matched
  int64_t t_ns = 0, matched_t_ns = 0;     // their timestamps
  uint32_t agent = 0, matched_agent = 0;  // their agents (differ in a merged map)
  int matches = 0;                        // map points matched across the loop
  double scale = 1;                       // Sim(3) scale of the correction (1 for stereo/RGB-D)
  double correction_m = 0;                // how far the closing keyframe moved
  double correction_ms = 0;               // fusion + essential graph
};

// A verified loop: the corrected pose of the current keyframe (S_cw), its loop-side point per
// keypoint (matched) and the points of the candidate and its neighbours (nearby).
struct LoopMatch : PlaceMatch {
  KeyFrameHandle candidate;
};

struct LoopClosingState {
  struct ConsistentGroup {
    std::vector<KeyFrameHandle> keyframes;  // sorted
    int count = 0;
  };
  std::vector<ConsistentGroup> consistent_groups;
  size_t keyframes_since_loop = 0;
  std::vector<LoopClosure> closures;
  std::mt19937_64 rng;  // RANSAC of the verification
  // A merged map's loops (merge/merged_loops.h): the correction moves only the current keyframe's
  // agent; every other agent's keyframes hold, as a merge holds the map merged into. The loop
  // measures the agent's own drift; the seams already tie it to the others, and freeing them
  // bends maps whose own loops were closed.
  bool hold_other_agents = false;

  explicit LoopClosingState(uint64_t seed = 2) : rng(seed) {}
};

// Indexes the keyframe (it must have its bag of words) and, unless search is false (loop closing
// off, a global BA running) or a loop was closed under 10 keyframes ago, looks for a loop.
// Returns a verified loop with at least min_loop_matches matches, or none.
[[nodiscard]] std::optional<LoopMatch> DetectLoop(const Map& map, KeyFrameDatabase& database, LoopClosingState& state,
                                                  const SystemContext& context, KeyFrameHandle current, bool search);

// Corrects the map for a verified loop and records it in state.closures.
void CorrectLoop(Map& map, LoopClosingState& state, const SystemContext& context, KeyFrameHandle current,
                 const LoopMatch& match);

// Global bundle adjustment after a loop: every keyframe free but `anchor` (the gauge), points with
// two observers or more. Build returns false when there is nothing to solve.
bool BuildGlobalBundleAdjustment(const Map& map, const SystemContext& context, KeyFrameHandle anchor,
                                 MapBundleAdjustment* ba);
// The solve: sparse Schur, ended early (and its result to be dropped) when stop returns true.
[[nodiscard]] BundleAdjustmentResult SolveGlobalBundleAdjustment(MapBundleAdjustment& ba, const SystemContext& context,
                                                                 std::function<bool()> stop);
// Writes the solution back: solved keyframes and points take it, keyframes made since follow
// their spanning-tree parent, other points the keyframe that made them.
void ApplyGlobalBundleAdjustment(Map& map, const SystemContext& context, const MapBundleAdjustment& ba,
                                 const BundleAdjustmentResult& result);

}  // namespace flatslam
