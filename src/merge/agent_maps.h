// The map server's maps of live agents: one map per agent session, grown from the keyframe
// messages the agents send (storage/keyframe_message.h), ready to merge (merge/map_merge.h).
// A point is joined across keyframes by the agent's id for it. A keyframe that arrives again (an
// agent's final update after its loop closures, a writer that resends) updates the keyframe's
// pose and its points' positions instead of adding anything. An agent that restarts
// sends under a new session id and gets a new map: its old map is kept, and the merge joins the
// two where they overlap.
// Concurrency: one thread at a time (the server's main loop).
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <unordered_map>
#include <utility>
#include <vector>

#include "ecs/map.h"
#include "io/calibration.h"
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
  [[nodiscard]] const std::vector<Session>& sessions() const { return sessions_; }
  // The camera of the first message (the agents of one server share a camera model).
  [[nodiscard]] const std::optional<AgentCamera>& camera() const { return camera_; }
  // The maps, by agent, with their keyframes' bags of words, ready for MergeAllMaps; the sessions
  // are left empty.
  [[nodiscard]] std::vector<Map> TakeMaps(const Vocabulary& vocabulary);

 private:
  struct Index {
    std::unordered_map<uint64_t, PointHandle> points;        // the agent's point id -> this map's point
    std::unordered_map<uint64_t, KeyFrameHandle> keyframes;  // the agent's keyframe id -> this map's
  };
  std::vector<Session> sessions_;
  std::vector<Index> index_;
  std::map<std::pair<uint32_t, uint64_t>, size_t> by_session_;
  std::optional<AgentCamera> camera_;
};

}  // namespace flatslam
