// An agent's keyframe as a message for the map server (schemas/agent.fbs): the keyframe (pose,
// keypoints, descriptors) and the map points it sees, with their positions as the agent has them
// when it sends, each point named by the agent's stable id so that the server joins the
// observations of one point from several keyframes. A point's other statistics (viewing
// direction, distance range, representative descriptor) follow from its observations, so the
// receiver computes them (Map::UpdatePointStats) instead of receiving them. Decoding verifies everything before it
// returns: a malformed message is an error, never a crash.
// Concurrency: pure functions; EncodeKeyFrameMessage reads the map (hold read access to it).
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "ecs/map.h"
#include "io/calibration.h"

namespace flatslam {

// An agent's camera, as map snapshots record it (SnapshotMetadata).
struct AgentCamera {
  Calibration calibration;
  MapScales scales;
  double rgbd_virtual_baseline_m = 0;  // RGB-D: the virtual baseline of the keyframes' right_u
};

struct KeyFrameMessage {
  uint32_t agent = 0;
  uint64_t session = 0;  // the agent process's run (a restarted agent sends under a new one)
  AgentCamera camera;
  KeyFrame keyframe;                       // identity, pose and keypoint columns; points null, no graph
  std::vector<uint32_t> keypoint_point;    // per keypoint: index into points, or kNoPoint
  std::vector<uint64_t> point_ids;         // per point: the agent's id (its packed handle)
  std::vector<Eigen::Vector3d> positions;  // per point, in the keyframe's world frame (sent in its camera frame)
  static constexpr uint32_t kNoPoint = 0xffffffffu;
};

// T_out_map and scale: the world frame the message's pose and points are written in, X_out = scale
// * R X_map + t (an agent whose map moved into a merged map's frame sends in its run's own frame;
// a monocular one's move has a scale).
[[nodiscard]] std::vector<uint8_t> EncodeKeyFrameMessage(
    const Map& map, KeyFrameHandle keyframe, uint32_t agent, uint64_t session, const AgentCamera& camera,
    const Eigen::Isometry3d& T_out_map = Eigen::Isometry3d::Identity(), double scale = 1.0);
// Throws flatslam::Error naming `what` (e.g. "keyframe message 12 from agent 1") and the first
// problem: not a keyframe message, a newer format, corrupt, columns of different sizes, a point
// index out of range, non-finite values.
[[nodiscard]] KeyFrameMessage DecodeKeyFrameMessage(std::span<const uint8_t> bytes, const std::string& what);

// Keyframes an agent's local mapping culled after it had sent them.
struct KeyFramesCulled {
  uint32_t agent = 0;
  uint64_t session = 0;
  std::vector<uint64_t> keyframes;  // the agent's keyframe ids
};

[[nodiscard]] std::vector<uint8_t> EncodeKeyFramesCulled(const KeyFramesCulled& message);
// Throws flatslam::Error naming `what` and the problem: not such a message, a newer format, corrupt.
[[nodiscard]] KeyFramesCulled DecodeKeyFramesCulled(std::span<const uint8_t> bytes, const std::string& what);

// The last message of an agent's run, after its final map update.
struct RunEnded {
  uint32_t agent = 0;
  uint64_t session = 0;
  uint64_t keyframes = 0;  // in the agent's final map
  uint64_t frames = 0;     // tracked
  bool stopped = false;    // by a signal, before the end of its dataset
  // Nonzero: the agent was killed and resumed from its checkpoint as this run, whose map holds this
  // run's keyframes up to the checkpoint (sent by the resumed run, not by the one that ended).
  uint64_t resumed_by = 0;
};

[[nodiscard]] std::vector<uint8_t> EncodeRunEnded(const RunEnded& message);
// Throws flatslam::Error naming `what` and the problem: not such a message, a newer format, corrupt.
[[nodiscard]] RunEnded DecodeRunEnded(std::span<const uint8_t> bytes, const std::string& what);

}  // namespace flatslam
