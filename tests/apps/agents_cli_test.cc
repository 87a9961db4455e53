// Live agents: one `flatslam server` and three `flatslam agent` processes on one machine (DDS over
// loopback), with an independent DDS subscriber in the test, as a ROS 2 node would be.
#include <unistd.h>

#include <algorithm>
#include <array>
#include <map>
#include <cmath>
#include <chrono>
#include <csignal>
#include <atomic>
#include <filesystem>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "cli.h"
#include "joint_ate.h"
#include "net/dds.h"
#include "storage/correction_message.h"
#include "test_data.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;
using testing::Contains;
using testing::ReadBytes;
using testing::RunApp;
using testing::Spawn;
using testing::Wait;

// Lines of a file (0 when it cannot be read).
size_t LineCount(const fs::path& path) {
  const std::string text = ReadBytes(path);
  return static_cast<size_t>(std::count(text.begin(), text.end(), '\n'));
}

// Polls `done` every 50 ms until it holds or `seconds` have passed.
template <typename Done>
void WaitUntil(Done done, int seconds) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(seconds);
  while (!done() && std::chrono::steady_clock::now() < deadline)
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
}

// Waits (at most 120 s) until a run writing to `out` has tracked `frames` frames (its stats.csv
// grows by a line a frame, after a header).
void WaitForTrackedFrames(const fs::path& out, size_t frames) {
  WaitUntil([&] { return LineCount(out / "stats.csv") >= frames + 1; }, 120);
}

// Every correction a subscriber heard, by agent run and merge.
using HeardCorrections = std::map<std::pair<uint64_t, uint64_t>, CorrectionMessage>;  // (session, revision)

// From an agent's summary: its run, and the frame its map ended in, from its run's own frame (the
// correction it last moved its map by; identity when it never moved it).
struct AgentFrame {
  uint64_t session = 0;
  unsigned long long moves = 0, by = 0;
  Eigen::Isometry3d T_map_run = Eigen::Isometry3d::Identity();  // X_map = scale * R X_run + t
  double scale = 1.0;                                           // a monocular run's
};
// The number just before `what` in `text` (-1 when `what` is not there).
long NumberBefore(const std::string& text, const std::string& what) {
  const size_t at = text.find(what);
  if (at == std::string::npos) return -1L;
  const size_t start = text.rfind(' ', at - 1) + 1;  // the number ends where `what` starts
  return std::stol(text.substr(start, at - start));
}

AgentFrame AgentFrameOf(const std::string& agent_log, const HeardCorrections& heard) {
  AgentFrame out;
  const size_t run = agent_log.find("; run ");
  EXPECT_NE(run, std::string::npos) << agent_log;
  if (run == std::string::npos) return out;
  out.session = std::stoull(agent_log.substr(run + 6, 16), nullptr, 16);
  // An agent that heard no correction while it ran says so instead.
  const size_t at = agent_log.find("its map moved into the merged map's frame ");
  if (at == std::string::npos) {
    EXPECT_TRUE(Contains(agent_log, "no correction from a server")) << agent_log;
    return out;
  }
  EXPECT_EQ(
      std::sscanf(agent_log.c_str() + at,
                  "its map moved into the merged map's frame %llu times (the last by merge %llu)", &out.moves, &out.by),
      2)
      << agent_log.substr(at, 120);
  if (out.moves == 0) return out;
  const auto it = heard.find({out.session, out.by});
  EXPECT_NE(it, heard.end()) << "moved by a correction not heard: merge " << out.by;
  if (it == heard.end()) return out;
  out.T_map_run.linear() = it->second.rotation;
  out.T_map_run.translation() = it->second.translation;
  out.scale = it->second.scale;
  return out;
}

// The agent's newest 10 keyframes (as it saved them, in its map's frame), taken back to its run's
// frame and moved by correction c, against the same keyframes in the server's map: RMS distance.
// The number of them found there goes to *found.
double NewestKeyFramesRms(const Trajectory& keyframes, const AgentFrame& frame, const CorrectionMessage& c,
                          const Trajectory& merged, size_t* found) {
  double sum = 0;
  *found = 0;
  for (size_t i = keyframes.size() >= 10 ? keyframes.size() - 10 : 0; i < keyframes.size(); ++i) {
    const Eigen::Vector3d run = frame.T_map_run.linear().transpose() *
                                (keyframes[i].T_world_cam.translation() - frame.T_map_run.translation()) / frame.scale;
    const Eigen::Vector3d moved = c.scale * (c.rotation * run) + c.translation;
    for (const TimedPose& m : merged) {
      if (m.t_ns != keyframes[i].t_ns) continue;
      sum += (moved - m.T_world_cam.translation()).squaredNorm();
      ++*found;
    }
  }
  return *found > 0 ? std::sqrt(sum / static_cast<double>(*found)) : 0.0;
}

// Every correction the server sends, heard by the test's own DDS subscriber.
class CorrectionListener {
 public:
  explicit CorrectionListener(uint32_t domain)
      : node_(Options(domain), "test subscriber"),
        reader_(node_.PayloadReader(kCorrectionTopic, [this](const Payload& payload) {
          if (payload.kind != PayloadKind::kCorrection) return;
          CorrectionMessage c = DecodeCorrectionMessage(payload.bytes, "correction");
          const std::lock_guard<std::mutex> lock(mutex_);
          heard_[{c.session, c.revision}] = std::move(c);
        })) {}
  [[nodiscard]] HeardCorrections Heard() const {
    const std::lock_guard<std::mutex> lock(mutex_);
    return heard_;
  }
  // Waits (at most 30 s) until the listener matched a server's correction writer: the topic is
  // volatile, so a correction written before that is never heard here.
  void WaitForServer() const {
    WaitUntil([&] { return reader_->matched() > 0; }, 30);
    EXPECT_GT(reader_->matched(), 0) << "the test's listener matched no correction writer";
  }

 private:
  static DdsOptions Options(uint32_t domain) {
    DdsOptions dds;
    dds.domain = domain;
    return dds;
  }
  mutable std::mutex mutex_;
  HeardCorrections heard_;
  DdsNode node_;
  std::unique_ptr<DdsNode::Reader<Payload>> reader_;  // last: stops before what it writes goes
};

// An agent run against the server's final map: the last correction heard for it, and the RMS
// distance NewestKeyFramesRms measures between its saved keyframes (taken back by the move it
// logged) moved by that correction and its keyframes in the map (exported for `agent` to
// `exported`). Fails the test and returns nullopt when something is missing.
struct LastCorrectionCheck {
  CorrectionMessage last;
  double rms = 0;
  size_t found = 0;
};
std::optional<LastCorrectionCheck> CheckAgainstLastCorrection(const fs::path& map, uint32_t agent,
                                                              const Trajectory& keyframes, const AgentFrame& frame,
                                                              const HeardCorrections& heard, const fs::path& exported) {
  const CorrectionMessage* last = nullptr;
  for (const auto& [key, c] : heard)
    if (key.first == frame.session) last = &c;  // ordered by session, then merge
  EXPECT_NE(last, nullptr) << "no correction heard for agent " << agent;
  if (!last) return std::nullopt;
  const auto r =
      RunApp("map export " + map.string() + " --trajectory " + exported.string() + " --agent " + std::to_string(agent));
  EXPECT_EQ(r.exit_code, 0) << r.output;
  if (r.exit_code != 0) return std::nullopt;
  LastCorrectionCheck out;
  out.last = *last;
  out.rms = NewestKeyFramesRms(keyframes, frame, *last, ReadTum(exported), &out.found);
  return out;
}

// A map server writing to dir/server (log dir/server.log) for `agents` agents on DDS domain d.
pid_t SpawnServer(const fs::path& dir, int agents, const std::string& d, const std::vector<std::string>& extra = {}) {
  std::vector<std::string> args = {"server", "--out", (dir / "server").string(), "--agents", std::to_string(agents)};
  args.insert(args.end(), extra.begin(), extra.end());
  args.insert(args.end(), {"--dds-domain", d});
  return Spawn(args, dir / "server.log");
}

// The town agents of the merge tests (tests/merge/map_merge_test.cc): agents 0 and 1 share two
// stretches of road, agent 2 shares the top road with both.
std::string Town(int agent) {
  return "synth:town:agent=" + std::to_string(agent) +
         ",width=480,height=360,fps=10,duration=" + (agent == 0 ? "36" : "55");
}

TEST(AgentsCli, ServerJoinsThreeAgentsInOneFrameAndASubscriberHearsTheirPoses) {
  const fs::path dir = testing::FreshTempDir("agents_cli");
  const uint32_t domain = 150 + static_cast<uint32_t>(getpid() % 50);  // apart from other test processes
  const std::string d = std::to_string(domain);

  DdsOptions dds;
  dds.domain = domain;
  DdsNode subscriber(dds, "test subscriber");
  // Poses in each agent's own frame (counted) and, once the server merged its map with others',
  // in the merged map's frame (kept, with the frame's name).
  std::mutex mutex;
  std::array<int, 3> poses{};
  std::array<std::vector<std::pair<std::string, TimedPose>>, 3> merged_poses;
  std::vector<std::unique_ptr<DdsNode::Reader<PoseStamped>>> readers;
  for (int k = 0; k < 3; ++k) {
    const std::string frame = "flatslam_agent_" + std::to_string(k) + "_map";
    readers.push_back(subscriber.PoseReader(AgentPoseTopic(k), [&, k, frame](const PoseStamped& p) {
      const Eigen::Quaterniond q(p.orientation[3], p.orientation[0], p.orientation[1], p.orientation[2]);
      if (std::abs(q.squaredNorm() - 1.0) > 1e-9) return;
      const std::lock_guard<std::mutex> lock(mutex);
      if (p.frame_id == frame) {
        ++poses[k];
      } else if (p.frame_id.rfind("flatslam_map_", 0) == 0) {
        TimedPose pose;
        pose.t_ns = int64_t{p.sec} * 1'000'000'000 + p.nanosec;
        pose.T_world_cam.linear() = q.toRotationMatrix();
        pose.T_world_cam.translation() = Eigen::Vector3d(p.position[0], p.position[1], p.position[2]);
        merged_poses[k].emplace_back(p.frame_id, pose);
      }
    }));
  }
  // The server's corrections, as the agents receive them.
  HeardCorrections every_correction;
  const auto correction_reader = subscriber.PayloadReader(kCorrectionTopic, [&](const Payload& payload) {
    if (payload.kind != PayloadKind::kCorrection || payload.agent >= 3) return;
    CorrectionMessage c = DecodeCorrectionMessage(payload.bytes, "correction");
    const std::lock_guard<std::mutex> lock(mutex);
    every_correction[{c.session, c.revision}] = std::move(c);
  });

  const pid_t server = SpawnServer(dir, 3, d);
  std::vector<pid_t> agents;
  for (int k = 0; k < 3; ++k)
    agents.push_back(Spawn({"agent", Town(k), "--id", std::to_string(k), "--quiet", "--deterministic", "--own-frame",
                            "--dds-domain", d, "--out", (dir / ("agent" + std::to_string(k))).string()},
                           dir / ("agent" + std::to_string(k) + ".log")));
  for (int k = 0; k < 3; ++k) ASSERT_EQ(Wait(agents[k]), 0) << ReadBytes(dir / ("agent" + std::to_string(k) + ".log"));
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string server_log = ReadBytes(dir / "server.log");
  EXPECT_TRUE(Contains(server_log, "0 dropped as malformed")) << server_log;
  for (const char* what : {"\nlive merge", "\nloops ", "\nfinal merge"})
    for (size_t pos = 0; (pos = server_log.find(what, pos)) != std::string::npos; ++pos)
      std::printf("%s\n", server_log.substr(pos + 1, server_log.find('\n', pos + 1) - pos - 1).c_str());
  for (size_t pos = 0; (pos = server_log.find("\nmet ", pos)) != std::string::npos; ++pos)
    std::printf("%s\n", server_log.substr(pos + 1, server_log.find('\n', pos + 1) - pos - 1).c_str());
  // The server merged the maps while the agents ran, and said when they met.
  EXPECT_TRUE(Contains(server_log, "\nmet           agent 0 run ")) << server_log;
  // The three agents end in one map: one frame.
  EXPECT_TRUE(Contains(server_log, "agents [0,1,2]")) << server_log;
  // The server stopped because every agent said its run ended, holding each one's final map.
  EXPECT_TRUE(Contains(server_log, "\nfinished      every agent's run ended (3 agents)")) << server_log;
  for (int k = 0; k < 3; ++k) {
    const size_t at = server_log.find("\nended         agent " + std::to_string(k) + " run ");
    ASSERT_NE(at, std::string::npos) << server_log;
    const std::string line = server_log.substr(at + 1, server_log.find('\n', at + 1) - at - 1);
    const size_t colon = line.find(": ");
    ASSERT_NE(colon, std::string::npos) << line;
    const size_t in_map = std::stoul(line.substr(colon + 2));
    EXPECT_GT(in_map, 0u) << line;
    EXPECT_TRUE(Contains(line, " keyframes in its map, " + std::to_string(in_map) + " held here")) << line;
  }
  // Agents 1 and 2 close their loops near the end of their runs (53 s): an agent sends the
  // keyframes it sent before again after a loop correction moved them, and the server applies
  // them as updates.
  long sent_again = 0;
  for (int k = 0; k < 3; ++k)
    sent_again += NumberBefore(ReadBytes(dir / ("agent" + std::to_string(k) + ".log")),
                               " sent again after its map's loop corrections");
  EXPECT_GT(sent_again, 0);
  const std::lock_guard<std::mutex> lock(mutex);
  for (int k = 0; k < 3; ++k) {
    const std::string log = ReadBytes(dir / ("agent" + std::to_string(k) + ".log"));
    // The server may have left by the time the agent prints its summary (it stops once every
    // agent said its run ended): one match during the run.
    EXPECT_TRUE(Contains(log, "; 1 server(s) matched (")) << log;
    EXPECT_TRUE(Contains(log, "), 0 writes failed")) << log;
    EXPECT_GT(poses[k], 0) << "the subscriber heard no pose of agent " << k;
  }

  // Each agent's keyframes in the server's map, under ONE alignment for all three, against the
  // keyframes of its own run (its own alignment): within 1.5x.
  std::vector<Trajectory> gt, merged;
  for (int k = 0; k < 3; ++k) {
    const fs::path agent_dir = dir / ("agent" + std::to_string(k));
    const fs::path exported = dir / ("merged" + std::to_string(k) + ".tum");
    const auto r = RunApp("map export " + (dir / "server" / "map.fsmap").string() + " --trajectory " +
                          exported.string() + " --agent " + std::to_string(k));
    ASSERT_EQ(r.exit_code, 0) << r.output;
    gt.push_back(ReadTum(agent_dir / "groundtruth.tum"));
    merged.push_back(ReadTum(exported));
    EXPECT_EQ(merged.back().size(), ReadTum(agent_dir / "keyframes.tum").size());
  }
  // The server's map under ONE alignment of all three adds at most half again to the error of the
  // agents' own runs (pooled over their keyframes), and keeps each agent's shape (aligned alone,
  // within 1.5x of its own run). Each agent's error under the one alignment is printed: it carries
  // the others' drift where no agent sees another (MapMerge.TownAgentsJoin...: the same agents).
  const JointAteResult joint = EvaluateJointAte(gt, merged);
  std::vector<double> own_ate;
  for (int k = 0; k < 3; ++k) {
    const double own = testing::JointAte({gt[k]}, {ReadTum(dir / ("agent" + std::to_string(k)) / "keyframes.tum")})[0];
    own_ate.push_back(own);
    std::printf(
        "agent %d: keyframe ATE own %.3f m, in the server's map (one alignment) %.3f m (%.2fx; aligned alone "
        "%.3f m)\n",
        k, own, joint.ate_m[k].rmse, joint.ate_m[k].rmse / own, joint.own_ate_m[k].rmse);
    EXPECT_LE(joint.own_ate_m[k].rmse, 1.5 * own) << "agent " << k;
  }
  const double own_pooled = testing::PooledRms(own_ate, joint.pairs);
  std::printf("all agents: own runs %.3f m, the server's map under one alignment %.3f m (%.2fx)\n", own_pooled,
              joint.all_m.rmse, joint.all_m.rmse / own_pooled);
  EXPECT_LE(joint.all_m.rmse, 1.5 * own_pooled);

  // The newest correction of each agent (each runs once here).
  std::array<std::optional<CorrectionMessage>, 3> corrections;
  for (const auto& [key, c] : every_correction) {
    auto& last = corrections.at(c.agent);
    if (!last || c.revision > last->revision) last = c;
  }
  // Corrections: every agent's last one places its map in agent 0's frame (the merged map keeps
  // the lowest agent's). It is the rigid fit of the agent's newest keyframes, where its camera is,
  // onto the server's map: those keyframes of its own run, moved by it, land where the server's
  // map has them up to the fit's residual, which the message carries. The residual is what the
  // server's map changed of the agent's shape there (its adjustment corrects shapes, which a rigid
  // correction cannot carry). Both maps are within their errors of the truth, so it stays within
  // the agent's own keyframe error; a correction fitted on the whole run, or misplaced, leaves the
  // newest keyframes off by the run's drift. With --own-frame (deterministic runs) the agents'
  // maps stay in their own frames.
  for (int k = 0; k < 3; ++k) {
    ASSERT_TRUE(corrections[k].has_value()) << "no correction for agent " << k << "\n" << server_log;
    const CorrectionMessage& c = *corrections[k];
    EXPECT_EQ(c.frame_agent, 0u);
    EXPECT_EQ(c.frame_session, corrections[0]->frame_session);
    EXPECT_EQ(c.runs, 3u);
    const AgentFrame frame = AgentFrameOf(ReadBytes(dir / ("agent" + std::to_string(k) + ".log")), every_correction);
    EXPECT_EQ(frame.session, c.session);
    EXPECT_EQ(frame.moves, 0u);
    const Trajectory keyframes = ReadTum(dir / ("agent" + std::to_string(k)) / "keyframes.tum");
    ASSERT_GE(keyframes.size(), 10u);
    size_t n = 0;
    const double rms = NewestKeyFramesRms(keyframes, frame, c, merged[k], &n);
    ASSERT_EQ(n, 10u) << "agent " << k;
    const double own = own_ate[k];
    std::printf(
        "agent %d: its newest 10 keyframes corrected are %.3f m from the server's map (fit: %.3f m; its own "
        "keyframe ATE %.3f m)\n",
        k, rms, c.rms_m, own);
    EXPECT_NEAR(rms, c.rms_m, 0.002) << "agent " << k;
    EXPECT_LE(rms, own) << "agent " << k;
  }
  // Agents that heard a correction while they ran published their later poses in the merged frame
  // (agents 1 and 2 run 55 s of frames, the maps meet after about 20 s of them). The frame may
  // change once more while they run (two agents meet before the third joins).
  auto frame_name = [](uint64_t session) {
    char id[48];
    std::snprintf(id, sizeof(id), "flatslam_map_%016llx", static_cast<unsigned long long>(session));
    return std::string(id);
  };
  const std::string final_frame = frame_name(corrections[0]->frame_session);
  // Every merged frame an agent published in is one the server placed it in (a correction to that
  // agent named it). Whether the last live merge reaches agents 1 and 2 before their runs end
  // depends on the machine's speed (they meet each other first; agent 0 joins a merge later), so
  // the final frame is not required of them.
  size_t in_merged_frames = 0;
  std::vector<Trajectory> heard_gt, heard;
  for (int k = 0; k < 3; ++k) {
    std::set<std::string> named;
    for (const auto& [key, c] : every_correction)
      if (c.agent == static_cast<uint32_t>(k)) named.insert(frame_name(c.frame_session));
    Trajectory in_final;
    for (const auto& [frame, pose] : merged_poses[k]) {
      EXPECT_TRUE(named.count(frame)) << "agent " << k << " published in " << frame << ", named by no correction to it";
      if (frame == final_frame) in_final.push_back(pose);
    }
    in_merged_frames += merged_poses[k].size();
    std::printf("agent %d: %d poses heard in its own frame, %zu in a merged frame, %zu of them in the final one\n", k,
                poses[k], merged_poses[k].size(), in_final.size());
    if (in_final.empty()) continue;
    heard_gt.push_back(gt[k]);
    heard.push_back(std::move(in_final));
  }
  EXPECT_GT(in_merged_frames, 0u) << "no agent published a pose in a merged frame";
  if (!heard.empty()) {
    const std::vector<double> live = testing::JointAte(heard_gt, heard);
    for (double ate : live) std::printf("poses heard in the final merged frame: ATE %.3f m (one alignment)\n", ate);
  }
  fs::remove_all(dir);
}

// Once two agents' maps have joined, later live merges grow the merged map by the keyframes the
// agents make instead of merging again (merge/live_merge.h): two town agents driving their loops
// for 80 s (they meet after about 20 s, close their loops at about 53 s and drive on).
TEST(AgentsCli, AServerGrowsTheMergedMapOnceAgentsJoined) {
  const fs::path dir = testing::FreshTempDir("agents_cli_grow");
  const std::string d = std::to_string(100 + getpid() % 20);
  const pid_t server = SpawnServer(dir, 2, d, {"--live-merge", "1"});
  std::vector<pid_t> agents;
  for (int k = 0; k < 2; ++k)
    agents.push_back(Spawn(
        {"agent", "synth:town:agent=" + std::to_string(k) + ",width=480,height=360,fps=10,duration=80", "--id",
         std::to_string(k), "--quiet", "--dds-domain", d, "--out", (dir / ("agent" + std::to_string(k))).string()},
        dir / ("agent" + std::to_string(k) + ".log")));
  for (int k = 0; k < 2; ++k) ASSERT_EQ(Wait(agents[k]), 0) << ReadBytes(dir / ("agent" + std::to_string(k) + ".log"));
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string log = ReadBytes(dir / "server.log");
  EXPECT_TRUE(Contains(log, "0 dropped as malformed")) << log;
  EXPECT_TRUE(Contains(log, "agents [0,1]")) << log;
  // Grown merges, each adding the keyframes since the last merge, every one placed in the map.
  size_t grown = 0, added = 0;
  for (size_t pos = 0; (pos = log.find(" grown at ", pos)) != std::string::npos; ++pos) {
    const std::string line = log.substr(pos, log.find('\n', pos) - pos);
    std::printf("%s\n", line.c_str());
    EXPECT_TRUE(Contains(line, "0 of runs in no merged map")) << line;
    EXPECT_TRUE(Contains(line, " of 2 runs")) << line;
    ++grown;
    added += static_cast<size_t>(std::max(0L, NumberBefore(line, " keyframes added")));
  }
  EXPECT_GT(grown, 0u) << log;
  EXPECT_GT(added, 0u) << log;
  // The agents heard corrections and sent their maps again after their loops.
  for (int k = 0; k < 2; ++k) {
    const std::string agent_log = ReadBytes(dir / ("agent" + std::to_string(k) + ".log"));
    EXPECT_TRUE(Contains(agent_log, " corrections from the server")) << agent_log;
    EXPECT_GT(NumberBefore(agent_log, " sent again after its map's loop corrections"), 0) << agent_log;
  }
  fs::remove_all(dir);
}

// A long session culls keyframes (the room's second lap revisits the first): the server removes
// each one the agent culled after sending it, so the server's map ends with the agent's keyframes.
TEST(AgentsCli, KeyFramesAnAgentCullsLeaveTheServersMap) {
  const fs::path dir = testing::FreshTempDir("agents_cli_cull");
  const std::string d = std::to_string(20 + getpid() % 60);
  const pid_t server = SpawnServer(dir, 1, d);
  const auto r = RunApp(
      "agent synth:room:duration=40,width=480,height=360 --id 0 --quiet --deterministic "
      "--dds-domain " +
      d + " --out " + (dir / "agent").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string log = ReadBytes(dir / "server.log");
  const long culled = NumberBefore(r.output, " culled after sending");
  EXPECT_GT(culled, 0) << r.output;
  EXPECT_EQ(NumberBefore(log, " keyframes removed as their agents culled them"), culled) << log;
  const size_t agent_keyframes = ReadTum(dir / "agent" / "keyframes.tum").size();
  EXPECT_TRUE(Contains(log, "agents [0], " + std::to_string(agent_keyframes) + " keyframes")) << log;
  fs::remove_all(dir);
}

// A server that starts while an agent is already mapping gets the agent's whole map: DDS keeps no
// history for it, so the agent sends every keyframe again when the server matches.
TEST(AgentsCli, ALateServerGetsTheWholeMap) {
  const fs::path dir = testing::FreshTempDir("agents_cli_late");
  const std::string d = std::to_string(80 + getpid() % 20);
  const fs::path agent_out = dir / "agent";
  const pid_t agent = Spawn({"agent", "synth:room:duration=40,width=480,height=360", "--id", "0", "--quiet",
                             "--deterministic", "--dds-domain", d, "--out", agent_out.string()},
                            dir / "agent.log");
  // The server starts once the agent has tracked 200 frames (stats.csv grows by a line a frame).
  WaitForTrackedFrames(agent_out, 200);
  const pid_t server = SpawnServer(dir, 1, d);
  ASSERT_EQ(Wait(agent), 0) << ReadBytes(dir / "agent.log");
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string agent_log = ReadBytes(dir / "agent.log"), log = ReadBytes(dir / "server.log");
  EXPECT_FALSE(Contains(agent_log, " 0 sent again to servers that joined later")) << agent_log;
  const size_t agent_keyframes = ReadTum(agent_out / "keyframes.tum").size();
  EXPECT_TRUE(Contains(log, "agents [0], " + std::to_string(agent_keyframes) + " keyframes")) << log;
  fs::remove_all(dir);
}

// An agent whose run ends before any server matched it (DDS keeps no history for a server that
// matches later) says that no server holds its map; with --wait-for-server S it waits at its end
// for a server that starts after its last frame, and that server gets its whole map.
TEST(AgentsCli, AnAgentThatEndsUnheardSaysSoOrWaitsForALateServer) {
  const fs::path dir = testing::FreshTempDir("agents_cli_unheard");
  const std::string d = std::to_string(120 + getpid() % 30);
  const std::string scene = "synth:room:duration=3,width=480,height=360";
  const std::string warning = "warning: no server matched this agent, so no server holds its map";

  const auto alone = RunApp("agent " + scene + " --id 0 --quiet --deterministic --dds-domain " + d);
  ASSERT_EQ(alone.exit_code, 0) << alone.output;
  EXPECT_TRUE(Contains(alone.output, warning)) << alone.output;
  EXPECT_TRUE(Contains(alone.output, "0 server(s) matched")) << alone.output;

  for (const char* bad : {"-1", "soon"}) {
    const auto r = RunApp("agent " + scene + " --id 0 --quiet --dds-domain " + d + " --wait-for-server " + bad);
    EXPECT_EQ(r.exit_code, 2) << r.output;
    EXPECT_TRUE(Contains(r.output, "--wait-for-server")) << r.output;
  }
  const auto unpublished = RunApp("run " + scene + " --quiet --wait-for-server 5");
  EXPECT_EQ(unpublished.exit_code, 2) << unpublished.output;
  EXPECT_TRUE(Contains(unpublished.output, "--wait-for-server need --publish")) << unpublished.output;

  const fs::path agent_out = dir / "agent";
  const pid_t agent = Spawn({"agent", scene, "--id", "0", "--quiet", "--deterministic", "--dds-domain", d,
                             "--wait-for-server", "60", "--out", agent_out.string()},
                            dir / "agent.log");
  // The server starts once the agent, done with its frames, says it waits: without the wait it
  // would have ended there (as the run alone above did).
  WaitUntil([&] { return Contains(ReadBytes(dir / "agent.log"), "waiting up to 60 s for one"); }, 120);
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  const pid_t server = SpawnServer(dir, 1, d);
  ASSERT_EQ(Wait(agent), 0) << ReadBytes(dir / "agent.log");
  const std::string agent_log = ReadBytes(dir / "agent.log");
  if (!Contains(agent_log, "1 server(s) matched")) {
    ::kill(server, SIGTERM);  // it waits for an agent it never heard
    Wait(server);
    FAIL() << "the agent ended before the server matched it\n" << agent_log;
  }
  EXPECT_FALSE(Contains(agent_log, warning)) << agent_log;
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string log = ReadBytes(dir / "server.log");
  const size_t agent_keyframes = ReadTum(agent_out / "keyframes.tum").size();
  EXPECT_GT(agent_keyframes, 0u);
  EXPECT_TRUE(Contains(log, "agents [0], " + std::to_string(agent_keyframes) + " keyframes")) << log;
  fs::remove_all(dir);
}

// A killed agent never says its run ended: a server waiting for it stops after --idle S of
// silence, says so, and still writes the map of what it received.
TEST(AgentsCli, AServerWaitingForAKilledAgentStopsAfterItsSilence) {
  const fs::path dir = testing::FreshTempDir("agents_cli_silence");
  const std::string d = std::to_string(1 + getpid() % 19);
  const pid_t server = SpawnServer(dir, 1, d, {"--idle", "3"});
  const fs::path agent_out = dir / "agent";
  const pid_t agent = Spawn({"agent", "synth:room:duration=20,width=480,height=360", "--id", "0", "--quiet",
                             "--deterministic", "--dds-domain", d, "--out", agent_out.string()},
                            dir / "agent.log");
  WaitForTrackedFrames(agent_out, 100);
  // Killed once the server has heard it: an agent it never heard is not one of the N it waits for.
  WaitUntil([&] { return Contains(ReadBytes(dir / "server.log"), "\nheard         agent 0 run "); }, 120);
  ::kill(agent, SIGKILL);
  EXPECT_EQ(Wait(agent), 128 + SIGKILL);
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string log = ReadBytes(dir / "server.log");
  EXPECT_TRUE(Contains(log, "\nfinished      1 agents, nothing received for 3 s (0 of them ended their runs)")) << log;
  EXPECT_FALSE(Contains(log, "\nended ")) << log;
  EXPECT_TRUE(Contains(log, "agents [0], ")) << log;
  EXPECT_TRUE(fs::exists(dir / "server" / "map.fsmap"));
  fs::remove_all(dir);
}

// Options a server cannot run with are refused before it joins DDS, naming the option.
TEST(AgentsCli, ServerRefusesBadOptionsNamingThem) {
  const fs::path dir = testing::FreshTempDir("agents_cli_usage");
  const std::string out = " --out " + (dir / "server").string();
  struct Case {
    std::string arguments, message;
  };
  for (const Case& c : {Case{"server --live-merge 2", "server needs --out DIR"},
                        Case{"server" + out + " --live-merge -1", "--live-merge: seconds between live merges"},
                        Case{"server" + out + " --live-merge soon", "--live-merge"},
                        Case{"server" + out + " --idle 5", "--idle S needs --agents N"},
                        Case{"server" + out + " --agents -1", "--agents N"},
                        Case{"server" + out + " --agents 2 --idle -3", "--idle S"}}) {
    const auto r = RunApp(c.arguments);
    EXPECT_EQ(r.exit_code, 2) << c.arguments << "\n" << r.output;
    EXPECT_TRUE(Contains(r.output, c.message)) << c.arguments << "\n" << r.output;
  }
  fs::remove_all(dir);
}

// An agent killed mid-run (SIGKILL: no goodbye) and started again from a later frame: the server
// keeps the keyframes of the killed run, and the restarted run's keyframes join agent 0's map.
TEST(AgentsCli, AKilledAgentRestartsAndItsLaterKeyFramesJoinTheServersMap) {
  const fs::path dir = testing::FreshTempDir("agents_cli_restart");
  const uint32_t domain = 200 + static_cast<uint32_t>(getpid() % 30);
  const std::string d = std::to_string(domain);
  // The corrections the agents get (the agents here move their maps by them: no --own-frame).
  const CorrectionListener listener(domain);
  const pid_t server = SpawnServer(dir, 2, d);
  listener.WaitForServer();
  const pid_t agent0 =
      Spawn({"agent", Town(0), "--id", "0", "--quiet", "--deterministic", "--dds-domain", d}, dir / "agent0.log");
  const fs::path first_out = dir / "agent1_first";
  const pid_t killed = Spawn(
      {"agent", Town(1), "--id", "1", "--quiet", "--deterministic", "--dds-domain", d, "--out", first_out.string()},
      dir / "agent1_first.log");
  // Killed once it has tracked 150 frames (stats.csv grows by a line a frame) and the server has
  // heard it: a run whose keyframes never reached the server has nothing there to keep (under a
  // loaded machine the agents' discovery can take longer than those frames).
  WaitForTrackedFrames(first_out, 150);
  WaitUntil([&] { return Contains(ReadBytes(dir / "server.log"), "\nheard         agent 1 run "); }, 120);
  ::kill(killed, SIGKILL);
  EXPECT_EQ(Wait(killed), 128 + SIGKILL);
  const size_t restart_at = LineCount(first_out / "stats.csv") - 1;
  ASSERT_GE(restart_at, 150u);
  const fs::path again_out = dir / "agent1_again";
  const pid_t restarted = Spawn({"agent", Town(1), "--id", "1", "--quiet", "--deterministic", "--dds-domain", d,
                                 "--first-frame", std::to_string(restart_at), "--out", again_out.string()},
                                dir / "agent1_again.log");
  ASSERT_EQ(Wait(restarted), 0) << ReadBytes(dir / "agent1_again.log");
  ASSERT_EQ(Wait(agent0), 0) << ReadBytes(dir / "agent0.log");
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string log = ReadBytes(dir / "server.log");
  // Two runs of agent 1, both with keyframes (in the order first heard: the killed run first).
  std::vector<std::pair<std::string, size_t>> runs;  // "agent N" line, keyframes
  size_t keyframes = 0;
  for (size_t pos = log.find("\nagent "); pos != std::string::npos; pos = log.find("\nagent ", pos + 1)) {
    const std::string line = log.substr(pos + 1, log.find('\n', pos + 1) - pos - 1);
    const size_t colon = line.find(": ");
    ASSERT_NE(colon, std::string::npos) << line;
    runs.emplace_back(line, std::stoul(line.substr(colon + 2)));
    EXPECT_GT(runs.back().second, 0u) << line;
    keyframes += runs.back().second;
  }
  size_t agent0_keyframes = 0, restarted_keyframes = 0, agent1_runs = 0;
  for (const auto& [line, n] : runs) {
    if (Contains(line, "agent 0 ")) agent0_keyframes = n;
    if (Contains(line, "agent 1 ") && ++agent1_runs == 2) restarted_keyframes = n;
  }
  ASSERT_EQ(agent1_runs, 2u) << log;
  // Nothing is lost: the output maps hold every keyframe of the three runs; the restarted run's
  // keyframes are in agent 0's map (the killed run's first frames may overlap nothing and stay apart).
  size_t written = 0, joined = 0;
  for (size_t pos = log.find("\noutput map "); pos != std::string::npos; pos = log.find("\noutput map ", pos + 1)) {
    const std::string line = log.substr(pos + 1, log.find('\n', pos + 1) - pos - 1);
    const size_t agents = line.find("agents [");
    ASSERT_NE(agents, std::string::npos) << line;
    const size_t n = std::stoul(line.substr(line.find("], ", agents) + 3));
    written += n;
    if (Contains(line, "agents [0,1]")) joined = n;
  }
  EXPECT_EQ(written, keyframes) << log;
  EXPECT_GE(joined, agent0_keyframes + restarted_keyframes) << log;

  // The restarted run moved its map into the merged map's frame (agent 0's) while it ran; what
  // it sent stayed in its run's frame: its newest keyframes, taken back by the correction it moved
  // by and moved by the last one, land where the server's map has them, as near as the server's
  // own fit of that correction says. A run whose sent or saved frame were mixed up would miss by
  // the move itself: 75-85 m here. The fit's residual is how much the server's map bent those
  // keyframes against the run's own shape (a correction is rigid, the merged map is adjusted as
  // a whole): 0.014-0.16 m in runs of this test, which is at times more than the run's own error
  // (0.06-0.11 m since the synthetic textures were registered), so it is bounded against the move.
  const HeardCorrections corrections = listener.Heard();
  const AgentFrame frame = AgentFrameOf(ReadBytes(dir / "agent1_again.log"), corrections);
  EXPECT_GE(frame.moves, 1u) << ReadBytes(dir / "agent1_again.log");
  const Trajectory again = ReadTum(again_out / "keyframes.tum");
  const auto check =
      CheckAgainstLastCorrection(dir / "server" / "map.fsmap", 1, again, frame, corrections, dir / "merged1.tum");
  ASSERT_TRUE(check.has_value());
  const CorrectionMessage* last = &check->last;
  EXPECT_EQ(last->frame_agent, 0u);
  const double rms = check->rms;
  const size_t n = check->found;
  const double own = testing::JointAte({ReadTum(again_out / "groundtruth.tum")}, {again})[0];
  std::printf(
      "restarted agent 1: map moved %llu times (last by merge %llu); newest 10 keyframes %.3f m from the "
      "server's map after the last correction (revision %u, fit %.3f m on %u keyframes; own keyframe ATE %.3f m)\n",
      frame.moves, frame.by, rms, static_cast<unsigned>(last->revision), last->rms_m, last->keyframes, own);
  // The newest keyframes' displacement by the run's move: what a mix-up would miss by.
  double move2 = 0;
  for (size_t k = again.size() - n; k < again.size(); ++k) {
    const Eigen::Vector3d p = again[k].T_world_cam.translation();
    const Eigen::Vector3d run =
        frame.T_map_run.linear().transpose() * (p - frame.T_map_run.translation()) / frame.scale;
    move2 += (p - run).squaredNorm();
  }
  const double move = n > 0 ? std::sqrt(move2 / static_cast<double>(n)) : 0.0;
  std::printf("restarted agent 1: its move displaced its newest keyframes by %.3f m\n", move);
  EXPECT_EQ(n, 10u);
  EXPECT_NEAR(rms, last->rms_m, 0.01);
  EXPECT_GT(move, 1.0);  // the check below has something to tell apart
  EXPECT_LT(rms, 0.01 * move);
  fs::remove_all(dir);
}

// Monocular agents move their maps too, with the merged map's scale: two monocular runs of the
// room (different seeds, so different scales) end in one map, each moved its map into the merged
// frame while it ran, and its saved keyframes, taken back by that move (a similarity) and moved by
// its last correction, land where the server's map has them, as near as the server's fit says.
TEST(AgentsCli, MonocularAgentsMoveTheirMapsWithTheMergedMapsScale) {
  const fs::path dir = testing::FreshTempDir("agents_cli_mono");
  const uint32_t domain = 60 + static_cast<uint32_t>(getpid() % 20);
  const std::string d = std::to_string(domain);
  const CorrectionListener listener(domain);
  // The agents run their 20 s of frames in a few seconds: live merges every half second, so that
  // one lands while both still run.
  const pid_t server = SpawnServer(dir, 2, d, {"--live-merge", "0.5"});
  listener.WaitForServer();
  std::vector<pid_t> agents;
  for (int k = 0; k < 2; ++k)
    agents.push_back(Spawn({"agent", "synth:room:sensor=mono,duration=20,width=480,height=360", "--seed",
                            std::to_string(k + 1), "--id", std::to_string(k), "--quiet", "--deterministic",
                            "--dds-domain", d, "--out", (dir / ("agent" + std::to_string(k))).string()},
                           dir / ("agent" + std::to_string(k) + ".log")));
  for (int k = 0; k < 2; ++k) ASSERT_EQ(Wait(agents[k]), 0) << ReadBytes(dir / ("agent" + std::to_string(k) + ".log"));
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  EXPECT_TRUE(Contains(ReadBytes(dir / "server.log"), "agents [0,1]")) << ReadBytes(dir / "server.log");
  const HeardCorrections corrections = listener.Heard();
  for (int k = 0; k < 2; ++k) {
    const fs::path out = dir / ("agent" + std::to_string(k));
    const AgentFrame frame = AgentFrameOf(ReadBytes(dir / ("agent" + std::to_string(k) + ".log")), corrections);
    EXPECT_GE(frame.moves, 1u) << ReadBytes(dir / ("agent" + std::to_string(k) + ".log"));
    const auto check = CheckAgainstLastCorrection(dir / "server" / "map.fsmap", k, ReadTum(out / "keyframes.tum"),
                                                  frame, corrections, dir / ("merged" + std::to_string(k) + ".tum"));
    ASSERT_TRUE(check.has_value());
    const CorrectionMessage* last = &check->last;
    const double rms = check->rms;
    const size_t n = check->found;
    std::printf(
        "monocular agent %d: map moved %llu times, the last by merge %llu with scale %.4f; newest 10 keyframes %.4f "
        "from the server's map after the last correction (revision %llu, scale %.4f, fit %.4f)\n",
        k, frame.moves, frame.by, frame.scale, rms, static_cast<unsigned long long>(last->revision), last->scale,
        last->rms_m);
    EXPECT_EQ(n, 10u);
    EXPECT_NEAR(rms, last->rms_m, 0.01);
  }
  fs::remove_all(dir);
}

TEST(AgentsCli, AKilledAgentResumesFromItsCheckpointAndReplacesItsRunOnTheServer) {
  const fs::path dir = testing::FreshTempDir("agents_cli_resume");
  const std::string d = std::to_string(230 + static_cast<uint32_t>(getpid() % 3));
  const pid_t server = SpawnServer(dir, 1, d, {"--idle", "60"});
  const fs::path out = dir / "agent", checkpoint = dir / "agent.fsck";
  const pid_t killed = Spawn({"agent", Town(1), "--id", "1", "--quiet", "--deterministic", "--dds-domain", d, "--out",
                              out.string(), "--checkpoint", checkpoint.string(), "--checkpoint-every", "1"},
                             dir / "killed.log");
  WaitForTrackedFrames(out, 250);
  WaitUntil([&] { return fs::exists(checkpoint); }, 60);
  ::kill(killed, SIGKILL);
  EXPECT_EQ(Wait(killed), 128 + SIGKILL);
  ASSERT_TRUE(fs::exists(checkpoint)) << ReadBytes(dir / "killed.log");

  // `flatslam run --resume` hands a live agent's checkpoint to the DDS executable, which goes on
  // publishing as the agent: every frame of the run is tracked in the end, the first part's too.
  const auto resumed = RunApp("run --resume " + checkpoint.string() + " --quiet");
  ASSERT_EQ(resumed.exit_code, 0) << resumed.output;
  EXPECT_TRUE(Contains(resumed.output, "frames        550 tracked")) << resumed.output;
  EXPECT_TRUE(Contains(resumed.output, "to rt/flatslam/agent_1/pose")) << resumed.output;
  EXPECT_EQ(LineCount(out / "trajectory.kitti"), 550u);
  const size_t run_at = resumed.output.find("; run ");
  ASSERT_NE(run_at, std::string::npos) << resumed.output;
  const std::string run = resumed.output.substr(run_at + 6, 16);

  // The server dropped the killed run's map on the resumed run's word and holds the resumed run's:
  // one run of agent 1, with every keyframe of the agent's final map.
  ASSERT_EQ(Wait(server), 0) << ReadBytes(dir / "server.log");
  const std::string log = ReadBytes(dir / "server.log");
  EXPECT_TRUE(Contains(log, "continues as run " + run + " from its checkpoint")) << log;
  const size_t saved = ReadTum(out / "keyframes.tum").size();
  ASSERT_GT(saved, 0u);
  EXPECT_TRUE(Contains(log, "agent 1       run " + run + ": " + std::to_string(saved) + " keyframes")) << log;
  EXPECT_EQ(log.find("agent 1       run "), log.rfind("agent 1       run ")) << log;  // one run of agent 1
  EXPECT_TRUE(Contains(log, "output map 0   inputs 0, agents [1], " + std::to_string(saved) + " keyframes")) << log;

  // `flatslam agent --resume` takes only an agent's checkpoint.
  const fs::path plain = dir / "plain.fsck";
  const auto plain_run = RunApp("run synth:room:duration=2 --quiet --checkpoint " + plain.string());
  ASSERT_EQ(plain_run.exit_code, 0) << plain_run.output;
  const auto refused = RunApp("agent --resume " + plain.string());
  EXPECT_NE(refused.exit_code, 0);
  EXPECT_TRUE(Contains(refused.output, "not the checkpoint of an agent")) << refused.output;
  fs::remove_all(dir);
}

}  // namespace
}  // namespace flatslam
