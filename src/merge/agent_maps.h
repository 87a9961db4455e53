// The map server's maps of live agents: one map per agent session, grown from the keyframe
// messages the agents send (storage/keyframe_message.h), ready to merge (merge/map_merge.h).
// A point is joined across keyframes by the agent's id for it. A keyframe that arrives again (an
// agent's final update after its loop closures, a writer that resends) updates the keyframe's
// pose and its points' positions instead of adding anything. An agent that restarts
// sends under a new session id and gets a new map: its old map is kept, and the merge joins the
// two where they overlap; one resumed from its checkpoint says which run it continues, whose map
// the server then drops (Drop), the resumed run sending those keyframes itself.
// Concurrency: one thread at a time (the server's main loop).
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <unordered_map>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "ecs/map.h"
#include "geometry/similarity.h"
#include "io/calibration.h"
#include "merge/map_merge.h"
#include "storage/keyframe_message.h"

namespace flatslam {

class Vocabulary;

class AgentMaps {
 public:
  struct Session {
    uint32_t agent = 0;
    uint64_t session = 0;
    Map map;
  };

  // Applies one message: true when it added a keyframe, false when it updated one already there
  // (same agent, session and keyframe id).
  bool Add(KeyFrameMessage&& message);
  // Removes the keyframes the agent culled (unknown ids are skipped: never sent, or gone already),
  // and points no keyframe sees any more. Returns how many were removed.
  size_t Cull(const KeyFramesCulled& message);
  // Forgets one run's map altogether (a run an agent resumed from its checkpoint: the resumed run
  // sends the same keyframes again). Returns the keyframes it held (0 for a run not heard of).
  size_t Drop(uint32_t agent, uint64_t session);
  [[nodiscard]] const std::vector<Session>& sessions() const { return sessions_; }
  // The camera of the first message (the agents of one server share a camera model).
  [[nodiscard]] const std::optional<AgentCamera>& camera() const { return camera_; }
  // The agent's ids of a run's keyframes and points, and the handles they have in its map.
  struct Ids {
    std::unordered_map<uint64_t, PointHandle> points;
    std::unordered_map<uint64_t, KeyFrameHandle> keyframes;
  };
  // The maps, by agent, with their keyframes' bags of words (computed once per keyframe), ready
  // for MergeAllMaps, and the agent run of each.
  struct RunMaps {
    std::vector<Map> maps;
    std::vector<std::pair<uint32_t, uint64_t>> runs;  // agent, session
    std::vector<Ids> ids;                             // per map
  };
  // Moves them out: the sessions are left empty.
  [[nodiscard]] RunMaps TakeMaps(const Vocabulary& vocabulary);
  // Messages carry points as positions: a point's viewing direction, distance range and
  // representative descriptor follow from the observations held here (Map::UpdatePointStats),
  // computed once per point named since the last time, when the maps are taken or copied (a point
  // seen by n keyframes would otherwise be computed n times over, in O(n^2) each, as its keyframes
  // arrive and again in the final update). sessions() shows them as last computed.
  void RefreshPointStats();
  // Copies, for a merge while messages keep arriving; of the runs in `only` when it is not empty.
  [[nodiscard]] RunMaps CopyMaps(const Vocabulary& vocabulary,
                                 const std::vector<std::pair<uint32_t, uint64_t>>& only = {});

 private:
  // Session indices by agent, then in the order each run was first heard: the merge keeps the
  // first map's frame, so the result does not depend on which agent happened to send first.
  [[nodiscard]] std::vector<size_t> MergeOrder() const;
  void ComputeBow(const Vocabulary& vocabulary);
  std::vector<Session> sessions_;
  std::vector<Ids> index_;
  std::map<std::pair<uint32_t, uint64_t>, size_t> by_session_;
  std::optional<AgentCamera> camera_;
  // Per session: points a message named since their statistics were last computed.
  std::vector<std::vector<PointHandle>> stale_points_;
};

// A map's keyframe poses (T_world_cam) by frame timestamp (one agent run never keyframes a frame
// twice): taken from each input before a merge, to find the same keyframes after it.
using KeyFramePoses = std::map<int64_t, Eigen::Isometry3d>;
[[nodiscard]] KeyFramePoses PosesOf(const Map& map);

// Where one input map's frame sits in the output map that holds it: X_out = S * X_in, from the
// input's keyframes found in both (by agent and timestamp; a timestamp two runs of the agent
// share in one output map is ambiguous and left out): the rotation is the mean of the keyframes'
// rotation changes, the scale the ratio of their centres' spreads (1 when fixed), the translation
// what brings the centroids together. From orientations, not centres alone, so that a window of
// keyframes on a straight road still fixes the rotation about it.
struct RunFrame {
  size_t output = 0;  // index into MultiMapMerge::maps
  Similarity3 S_output_input;
  size_t keyframes = 0;  // used in the fit
  double rms = 0;        // of their centres after it, output units
};
// For every input of `merged` (agents[i] and poses[i] taken from input i before the merge): its
// frame in its output map, or nullopt when it stays alone in a map of its own or fewer than 2 of
// its keyframes are found. newest > 0 fits on the input's newest keyframes only: where the input's
// camera is now, what a live agent's correction is for (its older keyframes carry drift the
// merged map took out). fix_scale: stereo, RGB-D.
[[nodiscard]] std::vector<std::optional<RunFrame>> FitRunFrames(const MultiMapMerge& merged,
                                                                const std::vector<uint32_t>& agents,
                                                                const std::vector<KeyFramePoses>& poses, bool fix_scale,
                                                                size_t newest = 0);

}  // namespace flatslam
