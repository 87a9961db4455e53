// A running SLAM session as a live agent on DDS (`flatslam agent`, `flatslam run --publish`; in
// flatslam-live only, see live.h):
// every tracked frame's pose as a ROS 2 geometry_msgs/PoseStamped on rt/flatslam/agent_N/pose
// (best effort), every mapped keyframe as a keyframe message on flatslam/keyframes (reliable;
// when a server joins later, and after a loop correction of the map once the global bundle
// adjustment after it ended, every keyframe sent before again, before the next one), with byte
// counts for the bandwidth report. It listens on
// flatslam/corrections for the server's corrections of its run: once its map has been merged with
// others', the poses it publishes are in the merged map's frame (frame_id flatslam_map_<run of
// that frame>) instead of its own (flatslam_agent_N_map), as a ROS map -> odom correction would
// place them. A stereo or RGB-D agent also moves its map into that frame (between keyframes, on
// the mapping lane; unless --own-frame), so that its map, saved trajectory and later keyframes
// are in it; it still sends keyframes in its run's own frame, the one the server keeps its map in.
// A run resumed from an agent's checkpoint (--resume) first tells each server it meets that it
// replaces the run it continues (a run-ended message with resumed_by), then sends its whole map.
// Concurrency: OnFrame from the track stage, OnKeyFrame from the mapping lane, corrections on
// the DDS listener thread (the latest one is kept under a mutex); the counters are atomic; Finish
// and Summary after the run.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "geometry/similarity.h"
#include "live.h"
#include "net/dds.h"
#include "slam/session.h"
#include "storage/correction_message.h"
#include "storage/keyframe_message.h"

namespace flatslam::app {

// Options shared by the commands that join DDS: --dds-domain D and --dds-peers A,B (IPv4
// addresses for unicast discovery; "multicast" for DDS's default discovery).
DdsOptions ParseDdsOptions(const std::string& domain, const std::string& peers);

// The frame_id of poses in a merged map: the run whose frame that map keeps.
[[nodiscard]] std::string MergedFrameId(uint64_t frame_session);

class AgentLink : public AgentPublisher {
 public:
  // move_map: a stereo or RGB-D map moves into the merged map's frame with each newer correction.
  // run: this run's id; resumes: the run it continues from its checkpoint (0: none), which it
  // tells each server it meets to drop, sending the keyframes of the map it resumed instead.
  // wait_for_server_s: how long the end of a run that no server matched waits for one.
  AgentLink(uint32_t agent, const DdsOptions& dds, const AgentCamera& camera, bool move_map, uint64_t run,
            uint64_t resumes, double wait_for_server_s);
  void OnFrame(const FrameReport& report) override;
  // Moves the map into the merged map's frame first when a newer correction came (stereo and
  // RGB-D), then sends the keyframe.
  void OnKeyFrame(SlamSession& slam, KeyFrameHandle keyframe) override;
  // At the end of the run: when no server has matched yet, first waits up to wait_for_server_s for
  // one (the writer keeps no history for a reader that matches later); then every keyframe again,
  // as loop closures and bundle adjustment left it, so the server's copy ends as the agent's map
  // does; then the run-ended message.
  void PublishFinalMap(const SlamSession& slam) override;
  bool Finish(double seconds) override;
  [[nodiscard]] int servers_matched() const override;
  [[nodiscard]] std::string Summary() const override;

 private:
  uint32_t agent_;
  bool move_map_;
  uint64_t session_;
  uint64_t resumes_;
  double wait_for_server_s_;
  int announced_matches_ = 0;  // servers told that resumes_ is replaced (matches of the writer)
  bool seeded_ = false;        // the resumed map's keyframes are in sent_
  AgentCamera camera_;
  DdsNode node_;
  std::unique_ptr<DdsNode::Writer<PoseStamped>> poses_;
  std::unique_ptr<DdsNode::Writer<Payload>> keyframes_;
  mutable std::mutex correction_mutex_;
  std::optional<CorrectionMessage> correction_;  // the newest for this run
  uint64_t corrections_received_ = 0;
  // The map's world frame after each move, from the run's own (X_map = S X_run; first: the run's
  // own frame); a frame report's map_frame indexes it. Written on the mapping lane.
  std::vector<Similarity3> map_frames_{Similarity3{}};
  uint64_t moved_revision_ = 0;  // the correction the map was last moved by
  void MoveToNewestCorrection(SlamSession& slam);
  std::unique_ptr<DdsNode::Reader<Payload>> corrections_;  // last: stops before the rest goes
  void OnCorrection(const Payload& payload);
  // Writes one keyframe message; its size in bytes, 0 when nothing was written.
  size_t Send(const Map& map, KeyFrameHandle keyframe);
  // Keyframes sent and still in the map, with their ids (the mapping lane's, then the final
  // update's): one mapping culled since is reported to the server.
  std::vector<std::pair<KeyFrameHandle, uint64_t>> sent_;
  void SendCulled(const Map& map);
  // A run-ended message on the keyframe writer (this run's, or the one a resumed run replaces).
  void WriteRunEnded(const RunEnded& message);
  // A resumed run (none other): tells each server matched since the last call that this run
  // replaces resumes_.
  void AnnounceResumeToNewServers();
  // Matches of the keyframe writer already answered with the whole map (mapping lane).
  int answered_matches_ = 0;
  std::atomic<uint64_t> keyframes_sent_{0}, keyframe_bytes_{0}, updates_sent_{0}, update_bytes_{0}, poses_sent_{0},
      failed_{0}, sequence_{0}, culled_sent_{0}, resent_{0}, frames_tracked_{0}, map_moves_{0}, corrected_sent_{0},
      corrected_bytes_{0};
  uint64_t corrections_sent_ = 0;  // the session's map corrections when keyframes were last sent again
  std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
};

}  // namespace flatslam::app
