#include "agent_link.h"

#include <algorithm>
#include <cstdio>
#include <thread>

#include <Eigen/Geometry>

#include "args.h"
#include "stop_signals.h"

namespace flatslam::app {

DdsOptions ParseDdsOptions(const std::string& domain, const std::string& peers) {
  DdsOptions options;
  try {
    size_t used = 0;
    const unsigned long d = std::stoul(domain, &used);
    if (used != domain.size() || d > 232) throw std::invalid_argument(domain);
    options.domain = static_cast<uint32_t>(d);
  } catch (const std::exception&) {
    throw UsageError{"--dds-domain: expected a DDS domain id 0..232, got '" + domain + "'"};
  }
  options.peers.clear();
  if (peers != "multicast") {
    for (size_t pos = 0; pos <= peers.size();) {
      const size_t comma = std::min(peers.find(',', pos), peers.size());
      if (comma > pos) options.peers.push_back(peers.substr(pos, comma - pos));
      pos = comma + 1;
    }
    if (options.peers.empty()) throw UsageError{"--dds-peers: expected IPv4 addresses or 'multicast'"};
  }
  return options;
}

AgentLink::AgentLink(uint32_t agent, const DdsOptions& dds, const AgentCamera& camera, bool move_map, uint64_t run,
                     uint64_t resumes, double wait_for_server_s)
    : agent_(agent),
      move_map_(move_map),
      session_(run),
      resumes_(resumes),
      wait_for_server_s_(wait_for_server_s),
      camera_(camera),
      node_(dds, "flatslam agent " + std::to_string(agent)),
      poses_(node_.PoseWriter(AgentPoseTopic(agent))),
      keyframes_(node_.PayloadWriter(kKeyFrameTopic)),
      corrections_(node_.PayloadReader(kCorrectionTopic, [this](const Payload& p) { OnCorrection(p); })) {}

void AgentLink::OnCorrection(const Payload& payload) {
  if (payload.kind != PayloadKind::kCorrection || payload.agent != agent_) return;  // another agent's
  try {
    CorrectionMessage c = DecodeCorrectionMessage(
        payload.bytes, "correction " + std::to_string(payload.sequence) + " for agent " + std::to_string(agent_));
    if (c.session != session_) return;  // for an earlier run of this agent
    const std::lock_guard<std::mutex> lock(correction_mutex_);
    ++corrections_received_;
    if (!correction_ || c.revision > correction_->revision) correction_ = std::move(c);
  } catch (const Error& e) {
    std::fprintf(stderr, "warning: dropped %s\n", e.what());
  }
}

void AgentLink::OnFrame(const FrameReport& report) {
  if (!report.T_world_cam) return;
  ++frames_tracked_;
  PoseStamped pose;
  pose.sec = static_cast<int32_t>(report.t_ns / 1'000'000'000);
  pose.nanosec = static_cast<uint32_t>(report.t_ns % 1'000'000'000);
  std::optional<CorrectionMessage> correction;
  Similarity3 S_map_run;  // the frame the pose is in, from the run's
  {
    const std::lock_guard<std::mutex> lock(correction_mutex_);
    correction = correction_;
    S_map_run = map_frames_.at(std::min<size_t>(report.map_frame, map_frames_.size() - 1));
  }
  // The camera centre and orientation in the run's frame.
  const Similarity3 S_run_map = S_map_run.inverse();
  Eigen::Vector3d t = S_run_map * report.T_world_cam->translation();
  Eigen::Matrix3d R = S_run_map.R * report.T_world_cam->linear();
  if (correction) {
    // The camera centre and orientation in the merged map: X_merged = s R_c X + t_c.
    t = correction->scale * (correction->rotation * t) + correction->translation;
    R = correction->rotation * R;
    pose.frame_id = MergedFrameId(correction->frame_session);
  } else {
    pose.frame_id = "flatslam_agent_" + std::to_string(agent_) + "_map";
  }
  const Eigen::Quaterniond q(R);
  pose.position = {t.x(), t.y(), t.z()};
  pose.orientation = {q.x(), q.y(), q.z(), q.w()};
  if (poses_->Write(pose))
    ++poses_sent_;
  else
    ++failed_;
}

size_t AgentLink::Send(const Map& map, KeyFrameHandle keyframe) {
  if (!map.keyframes().contains(keyframe)) return 0;  // culled meanwhile
  Payload payload;
  payload.agent = agent_;
  payload.kind = PayloadKind::kKeyFrame;
  payload.sequence = sequence_++;
  // In the run's own frame, the one the server keeps the run's map in.
  const Similarity3 S_run_map = map_frames_.back().inverse();
  payload.bytes = EncodeKeyFrameMessage(map, keyframe, agent_, session_, camera_, S_run_map.RigidPart(), S_run_map.s);
  if (!keyframes_->Write(payload)) {
    ++failed_;
    return 0;
  }
  return payload.bytes.size();
}

void AgentLink::SendCulled(const Map& map) {
  KeyFramesCulled culled;
  culled.agent = agent_;
  culled.session = session_;
  std::erase_if(sent_, [&](const std::pair<KeyFrameHandle, uint64_t>& s) {
    if (map.keyframes().contains(s.first)) return false;
    culled.keyframes.push_back(s.second);
    return true;
  });
  if (culled.keyframes.empty()) return;
  Payload payload;
  payload.agent = agent_;
  payload.kind = PayloadKind::kCulled;
  payload.sequence = sequence_++;
  payload.bytes = EncodeKeyFramesCulled(culled);
  if (keyframes_->Write(payload))
    culled_sent_ += culled.keyframes.size();
  else
    ++failed_;
}

void AgentLink::MoveToNewestCorrection(SlamSession& slam) {
  Similarity3 S_new_old;
  {
    const std::lock_guard<std::mutex> lock(correction_mutex_);
    if (!move_map_ || !correction_ || correction_->revision <= moved_revision_) return;
    // Only a monocular map's scale is free; a stereo or RGB-D run's corrections have none.
    if (camera_.calibration.sensor != Sensor::kMonocular && correction_->scale != 1.0) return;
    const Similarity3 S_merged_run{correction_->rotation, correction_->translation, correction_->scale};
    S_new_old = S_merged_run * map_frames_.back().inverse();
    // Recorded before the move: a frame tracked after it finds its frame here.
    map_frames_.push_back(S_merged_run);
    moved_revision_ = correction_->revision;
  }
  slam.MoveMapFrame(S_new_old.RigidPart(), S_new_old.s);
  ++map_moves_;
}

void AgentLink::OnKeyFrame(SlamSession& slam, KeyFrameHandle keyframe) {
  MoveToNewestCorrection(slam);
  slam.ReadMap([&](const Map& map) {
    if (resumes_ != 0) {
      // A resumed run: every server it meets drops the run it continues (whose keyframes after the
      // checkpoint died with it) and gets the resumed map's keyframes from here, sent below.
      AnnounceResumeToNewServers();
      if (!seeded_) {
        seeded_ = true;
        for (KeyFrameHandle h : map.keyframes().handles())
          if (h != keyframe) sent_.emplace_back(h, map.keyframe(h).id);
      }
    }
    SendCulled(map);
    // A server that matched since the last keyframe (one that started late, or came back) has
    // none of the map yet: the writer keeps no history for it.
    if (const int matches = keyframes_->matches_ever(); matches > answered_matches_) {
      answered_matches_ = matches;
      for (const auto& [h, id] : sent_)
        if (Send(map, h) > 0) ++resent_;
    } else if (slam.map_corrections() > corrections_sent_ && !slam.global_bundle_adjustment_running()) {
      // A loop correction or a global bundle adjustment moved keyframes sent long ago: the
      // server's copies of them are stale until they come again. After a loop, once the global
      // bundle adjustment that follows it has ended: the map moves once more then.
      for (const auto& [h, id] : sent_) {
        if (const size_t bytes = Send(map, h); bytes > 0) {
          ++corrected_sent_;
          corrected_bytes_ += bytes;
        }
      }
    }
    // Whichever branch sent the map again sent it as these corrections left it.
    if (!slam.global_bundle_adjustment_running())
      corrections_sent_ = std::max(corrections_sent_, slam.map_corrections());
    if (const size_t bytes = Send(map, keyframe); bytes > 0) {
      ++keyframes_sent_;
      keyframe_bytes_ += bytes;
      sent_.emplace_back(keyframe, map.keyframe(keyframe).id);
    }
  });
}

void AgentLink::AnnounceResumeToNewServers() {
  if (resumes_ == 0) return;
  if (const int matches = keyframes_->matches_ever(); matches > announced_matches_) {
    announced_matches_ = matches;
    RunEnded replaced;
    replaced.agent = agent_;
    replaced.session = resumes_;
    replaced.stopped = true;
    replaced.resumed_by = session_;
    WriteRunEnded(replaced);
  }
}

void AgentLink::PublishFinalMap(const SlamSession& slam) {
  // A run that ends before discovery found a server (a short run, or one whose server starts
  // late) would otherwise end unheard. A stopped run does not wait: the user asked it to end.
  if (wait_for_server_s_ > 0 && keyframes_->matches_ever() == 0 && !g_stop) {
    std::fprintf(stderr, "\nno server has matched this agent yet: waiting up to %g s for one (--wait-for-server)\n",
                 wait_for_server_s_);
    std::fflush(stderr);
    const auto until = std::chrono::steady_clock::now() + std::chrono::duration<double>(wait_for_server_s_);
    while (keyframes_->matched() == 0 && !g_stop && std::chrono::steady_clock::now() < until)
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  AnnounceResumeToNewServers();
  RunEnded ended;
  ended.agent = agent_;
  ended.session = session_;
  ended.frames = frames_tracked_;
  ended.stopped = g_stop;
  slam.ReadMap([&](const Map& map) {
    SendCulled(map);
    for (KeyFrameHandle h : map.keyframes().handles()) {
      if (const size_t bytes = Send(map, h); bytes > 0) {
        ++updates_sent_;
        update_bytes_ += bytes;
      }
    }
    ended.keyframes = map.keyframes().size();
  });
  // Last on the same reliable writer, so a server that reads it has everything sent before.
  WriteRunEnded(ended);
}

void AgentLink::WriteRunEnded(const RunEnded& message) {
  Payload payload;
  payload.agent = agent_;
  payload.kind = PayloadKind::kRunEnded;
  payload.sequence = sequence_++;
  payload.bytes = EncodeRunEnded(message);
  if (!keyframes_->Write(payload)) ++failed_;
}

bool AgentLink::Finish(double seconds) {
  return keyframes_->matched() == 0 || keyframes_->WaitForAcknowledgments(seconds);
}

int AgentLink::servers_matched() const { return keyframes_->matches_ever(); }

std::string MergedFrameId(uint64_t frame_session) {
  char id[48];
  std::snprintf(id, sizeof(id), "flatslam_map_%016llx", static_cast<unsigned long long>(frame_session));
  return id;
}

std::string AgentLink::Summary() const {
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  const uint64_t n = keyframes_sent_, bytes = keyframe_bytes_;
  char line[640];
  std::snprintf(line, sizeof(line),
                "%llu keyframes to %s (%.1f KiB, %.1f KiB per keyframe, %.1f KiB/s over %.1f s), %llu culled "
                "after sending, %llu sent again to servers that joined later, final map update %llu keyframes "
                "(%.1f KiB), %llu poses to %s; %d server(s) matched (%d still at the end), %llu writes failed",
                static_cast<unsigned long long>(n), kKeyFrameTopic, bytes / 1024.0, n ? bytes / 1024.0 / n : 0.0,
                s > 0 ? bytes / 1024.0 / s : 0.0, s, static_cast<unsigned long long>(culled_sent_.load()),
                static_cast<unsigned long long>(resent_.load()), static_cast<unsigned long long>(updates_sent_.load()),
                update_bytes_ / 1024.0, static_cast<unsigned long long>(poses_sent_.load()),
                AgentPoseTopic(agent_).c_str(), keyframes_->matches_ever(), keyframes_->matched(),
                static_cast<unsigned long long>(failed_.load()));
  std::string summary = line;
  std::snprintf(line, sizeof(line), "; %llu sent again after its map's loop corrections (%.1f KiB)",
                static_cast<unsigned long long>(corrected_sent_.load()), corrected_bytes_ / 1024.0);
  summary += line;
  std::snprintf(line, sizeof(line), "; run %016llx", static_cast<unsigned long long>(session_));
  summary += line;
  const std::lock_guard<std::mutex> lock(correction_mutex_);
  if (correction_) {
    std::snprintf(line, sizeof(line),
                  "; %llu corrections from the server, the last (merge %llu): in the map of agent %u's run %016llx "
                  "with %u runs, scale %.4f, fitted on %u keyframes (rms %.3f)",
                  static_cast<unsigned long long>(corrections_received_),
                  static_cast<unsigned long long>(correction_->revision), correction_->frame_agent,
                  static_cast<unsigned long long>(correction_->frame_session), correction_->runs, correction_->scale,
                  correction_->keyframes, correction_->rms_m);
    summary += line;
    std::snprintf(line, sizeof(line), "; its map moved into the merged map's frame %llu times (the last by merge %llu)",
                  static_cast<unsigned long long>(map_moves_.load()), static_cast<unsigned long long>(moved_revision_));
    summary += line;
  } else {
    summary += "; no correction from a server (its map joined no other agent's yet)";
  }
  return summary;
}

int RunServerLive(const std::vector<std::string>& args);  // cmd_server.cc

void EnableLive() {
  g_make_agent_publisher = [](uint32_t agent, const LiveOptions& options,
                              const AgentCamera& camera) -> std::unique_ptr<AgentPublisher> {
    return std::make_unique<AgentLink>(agent, ParseDdsOptions(options.domain, options.peers), camera, options.move_map,
                                       options.run, options.resumes, options.wait_for_server_s);
  };
  g_run_server = &RunServerLive;
}

}  // namespace flatslam::app
