#include "merge/agent_maps.h"

#include <algorithm>

#include "place/vocabulary.h"

namespace flatslam {

bool AgentMaps::Add(KeyFrameMessage&& message) {
  const auto key = std::make_pair(message.agent, message.session);
  auto [it, inserted] = by_session_.emplace(key, sessions_.size());
  if (inserted) {
    sessions_.push_back(Session{message.agent, message.session, Map()});
    index_.emplace_back();
  }
  Session& session = sessions_[it->second];
  Index& index = index_[it->second];
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
  for (uint32_t k = 0; k < message.keypoint_point.size(); ++k) {
    const uint32_t i = message.keypoint_point[k];
    const PointHandle bound = map.keyframe(kf).points[k];
    if (i == KeyFrameMessage::kNoPoint) {
      // The agent unbound it since (a point culled or fused away): a point left unobserved goes.
      if (!bound.is_null()) map.EraseObservation(bound, kf, /*min_observations=*/1);
      continue;
    }
    MapPoint& sent = message.points[i];
    auto [found, is_new] = index.points.emplace(message.point_ids[i], PointHandle::null());
    if (is_new || !map.points().contains(found->second)) {
      sent.reference = kf;
      sent.first_keyframe_id = map.keyframe(kf).id;
      sent.observations.clear();
      found->second = map.points().create(MapPoint(sent));
    } else {
      MapPoint& point = map.point(found->second);
      point.position = sent.position;
      point.normal = sent.normal;
      point.descriptor = sent.descriptor;
      point.min_distance = sent.min_distance;
      point.max_distance = sent.max_distance;
    }
    const PointHandle p = found->second;
    if (bound == p) continue;
    if (!bound.is_null()) map.EraseObservation(bound, kf, /*min_observations=*/1);
    bool seen = false;
    for (const Observation& o : map.point(p).observations) seen = seen || o.keyframe == kf;
    if (!seen) map.AddObservation(p, kf, k);
  }
  map.UpdateCovisibility(kf);
  return added;
}

std::vector<Map> AgentMaps::TakeMaps(const Vocabulary& vocabulary) {
  // By agent, then in the order each run was first heard: the merge keeps the first map's frame,
  // so the result does not depend on which agent happened to send first.
  std::stable_sort(sessions_.begin(), sessions_.end(),
                   [](const Session& a, const Session& b) { return a.agent < b.agent; });
  std::vector<Map> maps;
  for (Session& session : sessions_) {
    for (KeyFrameHandle h : session.map.keyframes().handles()) {
      KeyFrame& kf = session.map.keyframe(h);
      vocabulary.Transform(kf.descriptor, &kf.bow, &kf.bow_features);
    }
    maps.push_back(std::move(session.map));
  }
  sessions_.clear();
  index_.clear();
  by_session_.clear();
  return maps;
}

}  // namespace flatslam
