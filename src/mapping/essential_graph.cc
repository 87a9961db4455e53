#include "mapping/essential_graph.h"

namespace flatslam {

EssentialGraph EssentialGraph::OfMap(const Map& map) {
  EssentialGraph g;
  g.nodes.assign(map.keyframes().handles().begin(), map.keyframes().handles().end());
  g.index.reserve(g.nodes.size());
  g.S.reserve(g.nodes.size());
  for (uint32_t i = 0; i < g.nodes.size(); ++i) {
    g.index.emplace(g.nodes[i], i);
    g.S.push_back(Similarity3::FromIsometry(map.keyframe(g.nodes[i]).T_cam_world));
  }
  g.S_before = g.S;
  g.fixed.assign(g.nodes.size(), false);
  return g;
}

void EssentialGraph::AddMapEdges(const Map& map, const std::vector<Similarity3>& measured, int min_covisibility,
                                 const std::function<bool(uint32_t, uint32_t)>& keep) {
  for (uint32_t i = 0; i < nodes.size(); ++i) {
    const KeyFrame& kf = map.keyframe(nodes[i]);
    auto relative = [&](KeyFrameHandle other) {
      const auto it = index.find(other);
      if (it == index.end() || !keep(i, it->second)) return;
      edges.Add(i, it->second, measured[i] * measured[it->second].inverse());
    };
    relative(kf.parent);
    for (KeyFrameHandle l : kf.loop_edges) relative(l);
    for (const auto& [n, w] : kf.covisible)
      if (w >= min_covisibility) relative(n);
  }
}

void EssentialGraph::Apply(Map* map, const std::function<KeyFrameHandle(PointHandle, const MapPoint&)>& follow) const {
  for (uint32_t i = 0; i < nodes.size(); ++i) map->keyframe(nodes[i]).T_cam_world = S[i].ToIsometry();
  for (PointHandle p : map->points().handles()) {
    MapPoint& point = map->point(p);
    const auto it = index.find(follow(p, point));
    if (it == index.end()) continue;
    point.position = S[it->second].inverse() * (S_before[it->second] * point.position);
  }
}

}  // namespace flatslam
