// A live map server's merged maps, grown between full merges. A full merge (MergeAllMaps) costs
// time in proportion to the maps: place recognition between every pair, appending, the essential
// graph and loop search over every keyframe. Once every agent's run has joined another's in a
// merged map, what changes between two merges is the keyframes the agents made since. A
// GrowingMerge keeps the merged maps of the last full merge and adds those keyframes to them:
//  - each new keyframe goes into the merged map that holds its run: its points join the merged
//    map's by the agent's ids, and the keyframe is placed by those it sees (pose optimization
//    from where the run's frame there puts it; the run's frame alone when it sees too few);
//  - a point new to the merged map goes where the placed keyframe sees it;
//  - a bundle adjustment frees the new keyframes and their best covisible neighbours, every other
//    keyframe that sees their points held (the merge's weld, around new keyframes, not a seam);
//  - loop closing continues over the new keyframes (MergedMapLoopCloser), where agents meet again;
//  - each run's frame is fitted again on its newest keyframes.
// Its cost follows the keyframes added, not the maps. Not followed: an agent's later changes to
// keyframes it sent before (sent again after its loop corrections, culls) move only the run's
// poses its frame is fitted on; the map server merges in full instead when a keyframe comes again
// (apps/flatslam/cmd_server.cc), and its final merge takes everything from the agents' maps.
// Concurrency: one thread at a time (the server's merge thread).
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <unordered_map>
#include <utility>
#include <vector>

#include "config/context.h"
#include "merge/agent_maps.h"
#include "merge/map_merge.h"
#include "place/loop_closing.h"
#include "storage/keyframe_message.h"

namespace flatslam {

class Vocabulary;

// Where a run's entities were in its map before a full merge, by the agent's ids: the timestamp of
// each keyframe, and the observations (keyframe timestamp, keypoint) of each point. Taken from the
// maps the merge is given (it consumes them), to find them in its output: a point is where the
// first of its keyframes that still binds that keypoint binds it (the merge may have fused it
// into another point, or dropped an observation as an outlier).
struct RunSightings {
  std::unordered_map<uint64_t, int64_t> keyframes;
  std::unordered_map<uint64_t, std::vector<std::pair<int64_t, uint32_t>>> points;
};
[[nodiscard]] RunSightings SightingsOf(const Map& map, const AgentMaps::Ids& ids);

struct GrowReport {
  size_t added = 0;             // keyframes added to the merged maps
  size_t placed_by_points = 0;  // of them, placed by the merged map's points they see
  size_t updated = 0;           // messages of keyframes held already: their run poses only
  size_t skipped = 0;           // messages of runs that are in no merged map with another run
  size_t welded_keyframes = 0, weld_outliers = 0;
  std::vector<LoopClosure> loops;  // closed, in order
  // Adding keyframes and points, the weld, loop closing, fitting the runs' frames.
  double join_ms = 0, weld_ms = 0, loops_ms = 0, fit_ms = 0;
};

class GrowingMerge {
 public:
  using Run = std::pair<uint32_t, uint64_t>;  // agent, session
  // From a full merge of the maps of `runs` (input i is runs[i]): sightings[i] from input i's map
  // and poses[i] its keyframe poses (PosesOf), both taken before the merge. The merge's loop
  // closers continue (options.close_loops). newest: keyframes each run's frame is fitted on;
  // fix_scale: stereo, RGB-D.
  GrowingMerge(MultiMapMerge merged, std::vector<Run> runs, const std::vector<RunSightings>& sightings,
               std::vector<KeyFramePoses> poses, const MergeCamera& camera, const MapMergeOptions& options,
               size_t newest);

  // Applies the keyframe messages received since the last full merge or growth, in the order
  // received (as AgentMaps::Add applied them). Keyframes need their bags of words: computed here.
  GrowReport Grow(const std::vector<KeyFrameMessage>& messages, const Vocabulary& vocabulary);

  [[nodiscard]] const MultiMapMerge& merged() const { return merged_; }
  [[nodiscard]] const std::vector<Run>& runs() const { return runs_; }
  // Per run: its frame in the output map that holds it (none: alone, or too few keyframes).
  [[nodiscard]] const std::vector<std::optional<RunFrame>>& frames() const { return frames_; }
  // The runs of `runs` that are not here in a merged map with another run: their messages cannot
  // grow the maps (Grow skips them).
  [[nodiscard]] std::vector<Run> Uncovered(const std::vector<Run>& runs) const;
  [[nodiscard]] bool Covers(const std::vector<Run>& runs) const { return Uncovered(runs).empty(); }
  // What one search for the runs apart did.
  struct ApartSearch {
    bool found = false;    // an overlap: a full merge joins it
    size_t queries = 0;    // keyframes that queried another map's keyframe database
    size_t keyframes = 0;  // of the runs apart (what a search from all of them queries)
  };
  // Whether any of `others` (the current maps of `runs`, runs it does not cover, with bags of
  // words) overlaps one of the merged maps here or another of them (FindMapOverlap): then a full
  // merge joins them; else the merged maps can go on growing while those runs stay apart. For each
  // pair of maps it takes the cheapest (in keyframes that query) of three searches: every keyframe
  // of either map queries the other's database (every pair of their keyframes checked), or each map
  // queries the other with its window: its keyframes made since the last search, plus the kSearchWindow x
  // min_consistent_pairs keyframes before them (the keyframes of one overlapping stretch, which must
  // agree min_consistent_pairs at a time, arrive over several searches); a run searched for the
  // first time since the full merge has all its keyframes in its window. Every pair of keyframes
  // with at least one new keyframe is checked, and once a run apart has grown large a search costs
  // in proportion to the keyframes made since the last one, not to the maps. Records what it
  // searched (not when it finds an overlap: the full merge that follows starts a new GrowingMerge).
  ApartSearch SearchRunsApart(const std::vector<Run>& runs, const std::vector<Map>& others,
                              const Vocabulary& vocabulary);
  // Keyframes of a window per consistent pair asked for: a stretch where one keyframe in four finds
  // its place still gathers min_consistent_pairs pairs in one search. Larger windows cost queries
  // at every search. An overlap whose keyframes find their place more sparsely than that is left
  // to the next full merge (the final one at the latest), which searches every keyframe.
  static constexpr size_t kSearchWindow = 4;
  [[nodiscard]] size_t keyframes() const;

 private:
  void Fit();
  // Adds the keyframe of `message` (run r, in a merged map) and joins or adds its points; the points
  // it observes go to *touched.
  KeyFrameHandle AddKeyFrame(const KeyFrameMessage& message, size_t r, const Vocabulary& vocabulary, GrowReport* report,
                             std::vector<PointHandle>* touched);

  struct RunIndex {
    std::unordered_map<uint64_t, KeyFrameHandle> keyframes;  // the agent's id -> merged map's
    std::unordered_map<uint64_t, PointHandle> points;
  };
  MultiMapMerge merged_;
  std::vector<Run> runs_;
  std::vector<RunIndex> index_;
  std::vector<KeyFramePoses> poses_;  // per run, in its own frame, newest estimate
  std::vector<std::optional<RunFrame>> frames_;
  MergeCamera camera_;
  MapMergeOptions options_;
  SystemContext context_;
  size_t newest_ = 0;
  // The newest keyframe id each map queried with in the last search of runs apart: per run apart
  // (its map's ids at the server), per merged map (a full merge searched all of them already).
  std::map<Run, uint64_t> apart_searched_;
  std::vector<std::optional<uint64_t>> merged_searched_;
};

}  // namespace flatslam
