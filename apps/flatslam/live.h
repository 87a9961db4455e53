// Live agents on DDS in the command line. Fast DDS's libraries cost every process that maps them
// about 7.6 MiB of resident memory and their start-up work, so only the flatslam-live executable
// links them: flatslam hands `agent`, `server` and `run --publish` to it (ExecLive), and
// flatslam-live fills in the hooks below (EnableLive) that those commands call.
// Concurrency: the hooks are set once in main, before any command runs.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "slam/session.h"
#include "storage/keyframe_message.h"

namespace flatslam::app {

// A session publishing as a live agent (agent_link.cc): OnFrame from the track stage, OnKeyFrame
// from the mapping lane, then PublishFinalMap, Finish and Summary after the run.
class AgentPublisher {
 public:
  virtual ~AgentPublisher() = default;
  virtual void OnFrame(const FrameReport& report) = 0;
  virtual void OnKeyFrame(SlamSession& slam, KeyFrameHandle keyframe) = 0;
  // Every keyframe again, as loop closures and bundle adjustment left it, then word that the run ended.
  virtual void PublishFinalMap(const SlamSession& slam) = 0;
  // Waits up to `seconds` for every matched server to acknowledge every keyframe; false on timeout.
  virtual bool Finish(double seconds) = 0;
  // Servers matched since the run started (0: no server holds anything this run sent).
  [[nodiscard]] virtual int servers_matched() const = 0;
  // Keyframes and bytes sent (per keyframe, per second), the final update, poses, servers matched.
  [[nodiscard]] virtual std::string Summary() const = 0;
};

// --dds-domain and --dds-peers as given (validated by the publisher).
struct LiveOptions {
  std::string domain = "0";
  std::string peers = "127.0.0.1";
  bool move_map = true;  // move a stereo/RGB-D map into the merged frame (false: --own-frame)
  uint64_t run = 0;      // the run's id on the servers
  uint64_t resumes = 0;  // nonzero: the run this one resumes from its checkpoint
  // --wait-for-server S: at the end of a run that no server has matched yet, wait up to S seconds
  // for one before sending the final map (0: end at once).
  double wait_for_server_s = 0;
};

// Set by EnableLive in flatslam-live; null in flatslam.
extern std::unique_ptr<AgentPublisher> (*g_make_agent_publisher)(uint32_t agent, const LiveOptions& options,
                                                                 const AgentCamera& camera);
extern int (*g_run_server)(const std::vector<std::string>& args);

// flatslam-live's main: fills in the hooks.
void EnableLive();
// Whether this command line needs flatslam-live (agent, server, or run with --publish).
[[nodiscard]] bool NeedsLive(int argc, char** argv);
// Replaces this process by flatslam-live (next to this executable) with the same arguments;
// returns only to print why it could not, then exits with 1.
[[noreturn]] void ExecLive(int argc, char** argv);

}  // namespace flatslam::app
