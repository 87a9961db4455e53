#include "merge/agent_maps.h"

#include <algorithm>
#include <cmath>
#include <map>

#include <Eigen/SVD>

#include "place/vocabulary.h"

namespace flatslam {

bool AgentMaps::Add(KeyFrameMessage&& message) {
  const auto key = std::make_pair(message.agent, message.session);
  auto [it, inserted] = by_session_.emplace(key, sessions_.size());
  if (inserted) {
    sessions_.push_back(Session{message.agent, message.session, Map()});
    index_.emplace_back();
    stale_points_.emplace_back();
  }
  Session& session = sessions_[it->second];
  Ids& index = index_[it->second];
  if (!camera_) camera_ = message.camera;
  Map& map = session.map;
  // A keyframe sent again carries the agent's latest estimate of its pose and of its points, and
  // the points fused into it since.
  const auto known = index.keyframes.find(message.keyframe.id);
  const bool added = known == index.keyframes.end();
  KeyFrameHandle kf;
  if (added) {
    const uint64_t agent_id = message.keyframe.id;
    KeyFrame keyframe = std::move(message.keyframe);
    keyframe.agent = message.agent;
    kf = map.AddKeyFrame(std::move(keyframe));
    index.keyframes.emplace(agent_id, kf);
  } else {
    kf = known->second;
    map.keyframe(kf).T_cam_world = message.keyframe.T_cam_world;
  }
  std::vector<PointHandle>& touched = stale_points_[it->second];
  for (uint32_t k = 0; k < message.keypoint_point.size(); ++k) {
    const uint32_t i = message.keypoint_point[k];
    const PointHandle bound = map.keyframe(kf).points[k];
    if (i == KeyFrameMessage::kNoPoint) {
      // The agent unbound it since (a point culled or fused away): a point left unobserved goes.
      if (!bound.is_null()) map.EraseObservation(bound, kf, /*min_observations=*/1);
      continue;
    }
    auto [found, is_new] = index.points.emplace(message.point_ids[i], PointHandle::null());
    if (is_new || !map.points().contains(found->second)) {
      found->second = map.AddPoint(message.positions[i], kf);
    } else {
      map.point(found->second).position = message.positions[i];
    }
    const PointHandle p = found->second;
    touched.push_back(p);
    if (bound == p) continue;
    if (!bound.is_null()) map.EraseObservation(bound, kf, /*min_observations=*/1);
    bool seen = false;
    for (const Observation& o : map.point(p).observations) seen = seen || o.keyframe == kf;
    if (!seen) map.AddObservation(p, kf, k);
  }
  map.UpdateCovisibility(kf);
  return added;
}

void AgentMaps::RefreshPointStats() {
  if (!camera_) return;
  for (size_t i = 0; i < sessions_.size(); ++i) {
    Map& map = sessions_[i].map;
    std::vector<PointHandle>& stale = stale_points_[i];
    std::sort(stale.begin(), stale.end());
    stale.erase(std::unique(stale.begin(), stale.end()), stale.end());
    for (PointHandle p : stale)
      if (map.points().contains(p)) map.UpdatePointStats(p, camera_->scales);
    stale.clear();
  }
}

size_t AgentMaps::Cull(const KeyFramesCulled& message) {
  const auto it = by_session_.find({message.agent, message.session});
  if (it == by_session_.end()) return 0;
  Map& map = sessions_[it->second].map;
  auto& keyframes = index_[it->second].keyframes;
  size_t removed = 0;
  for (uint64_t id : message.keyframes) {
    const auto found = keyframes.find(id);
    if (found == keyframes.end()) continue;
    const KeyFrameHandle kf = found->second;
    keyframes.erase(found);
    if (!map.keyframes().contains(kf)) continue;
    // A point the culled keyframe alone saw goes with it; one that others see stays.
    const std::vector<PointHandle> seen = map.keyframe(kf).points;
    for (PointHandle p : seen)
      if (!p.is_null()) map.EraseObservation(p, kf, /*min_observations=*/1);
    map.EraseKeyFrame(kf);
    ++removed;
  }
  return removed;
}

size_t AgentMaps::Drop(uint32_t agent, uint64_t session) {
  const auto it = by_session_.find({agent, session});
  if (it == by_session_.end()) return 0;
  const size_t i = it->second;
  const size_t held = sessions_[i].map.keyframes().size();
  sessions_.erase(sessions_.begin() + static_cast<std::ptrdiff_t>(i));
  index_.erase(index_.begin() + static_cast<std::ptrdiff_t>(i));
  stale_points_.erase(stale_points_.begin() + static_cast<std::ptrdiff_t>(i));
  by_session_.erase(it);
  for (auto& [key, index] : by_session_)
    if (index > i) --index;
  return held;
}

std::vector<size_t> AgentMaps::MergeOrder() const {
  std::vector<size_t> order(sessions_.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return sessions_[a].agent < sessions_[b].agent; });
  return order;
}

void AgentMaps::ComputeBow(const Vocabulary& vocabulary) {
  // Descriptors never change once a keyframe is here (an update moves pose and points only).
  for (Session& session : sessions_) ComputeKeyFrameBow(session.map, vocabulary, /*missing_only=*/true);
}

AgentMaps::RunMaps AgentMaps::TakeMaps(const Vocabulary& vocabulary) {
  ComputeBow(vocabulary);
  RefreshPointStats();
  RunMaps taken;
  for (size_t i : MergeOrder()) {
    taken.maps.push_back(std::move(sessions_[i].map));
    taken.runs.emplace_back(sessions_[i].agent, sessions_[i].session);
    taken.ids.push_back(std::move(index_[i]));
  }
  sessions_.clear();
  index_.clear();
  stale_points_.clear();
  by_session_.clear();
  return taken;
}

AgentMaps::RunMaps AgentMaps::CopyMaps(const Vocabulary& vocabulary,
                                       const std::vector<std::pair<uint32_t, uint64_t>>& only) {
  ComputeBow(vocabulary);
  RefreshPointStats();
  RunMaps copies;
  for (size_t i : MergeOrder()) {
    const std::pair<uint32_t, uint64_t> run{sessions_[i].agent, sessions_[i].session};
    if (!only.empty() && std::find(only.begin(), only.end(), run) == only.end()) continue;
    copies.maps.push_back(sessions_[i].map);
    copies.runs.emplace_back(sessions_[i].agent, sessions_[i].session);
    copies.ids.push_back(index_[i]);
  }
  return copies;
}

KeyFramePoses PosesOf(const Map& map) {
  KeyFramePoses poses;
  for (const KeyFrame& kf : map.keyframes().values()) poses[kf.t_ns] = kf.T_cam_world.inverse();
  return poses;
}

std::vector<std::optional<RunFrame>> FitRunFrames(const MultiMapMerge& merged, const std::vector<uint32_t>& agents,
                                                  const std::vector<KeyFramePoses>& poses, bool fix_scale,
                                                  size_t newest) {
  std::vector<std::optional<RunFrame>> frames(poses.size());
  for (size_t g = 0; g < merged.maps.size(); ++g) {
    if (merged.members[g].size() < 2) continue;
    // Each agent's keyframes in this output map by timestamp; a timestamp seen twice is ambiguous.
    std::map<std::pair<uint32_t, int64_t>, std::optional<Eigen::Isometry3d>> out;
    for (const KeyFrame& kf : merged.maps[g].keyframes().values()) {
      auto [it, inserted] = out.try_emplace({kf.agent, kf.t_ns}, kf.T_cam_world.inverse());
      if (!inserted) it->second.reset();
    }
    for (size_t input : merged.members[g]) {
      std::vector<std::pair<Eigen::Isometry3d, Eigen::Isometry3d>> pairs;  // input, output; newest first
      for (auto it = poses[input].rbegin(); it != poses[input].rend(); ++it) {
        const auto found = out.find({agents[input], it->first});
        if (found == out.end() || !found->second) continue;
        pairs.emplace_back(it->second, *found->second);
        if (newest > 0 && pairs.size() == newest) break;
      }
      if (pairs.size() < 2) continue;
      const double n = static_cast<double>(pairs.size());
      Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
      Eigen::Vector3d mean_in = Eigen::Vector3d::Zero(), mean_out = Eigen::Vector3d::Zero();
      for (const auto& [in, o] : pairs) {
        M += o.linear() * in.linear().transpose();
        mean_in += in.translation() / n;
        mean_out += o.translation() / n;
      }
      // The rotation nearest the mean of the rotation changes (chordal mean).
      const Eigen::JacobiSVD<Eigen::Matrix3d> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
      Eigen::Matrix3d D = Eigen::Matrix3d::Identity();
      D(2, 2) = (svd.matrixU() * svd.matrixV().transpose()).determinant() < 0 ? -1 : 1;
      Similarity3 S;
      S.R = svd.matrixU() * D * svd.matrixV().transpose();
      double spread_in = 0, spread_out = 0;
      for (const auto& [in, o] : pairs) {
        spread_in += (in.translation() - mean_in).squaredNorm();
        spread_out += (o.translation() - mean_out).squaredNorm();
      }
      S.s = fix_scale || spread_in <= 0 ? 1.0 : std::sqrt(spread_out / spread_in);
      S.t = mean_out - S.s * (S.R * mean_in);
      double sum = 0;
      for (const auto& [in, o] : pairs) sum += (S * in.translation() - o.translation()).squaredNorm();
      frames[input] = RunFrame{g, S, pairs.size(), std::sqrt(sum / n)};
    }
  }
  return frames;
}

}  // namespace flatslam
