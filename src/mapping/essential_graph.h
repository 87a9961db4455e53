// The essential graph of a map (every keyframe a node; spanning tree, loop edges and strong
// covisibility as edges) and how its solution is written back: keyframes take their optimized
// poses and each point moves with the keyframe it follows. Loop correction and map merging build
// it the same way and differ only in the poses an edge is measured from and the edges they add.
// Concurrency: built from and applied to a map the caller holds exclusively.
#pragma once

#include <cstdint>
#include <functional>
#include <unordered_map>
#include <vector>

#include "ecs/map.h"
#include "geometry/similarity.h"

namespace flatslam {

struct EssentialGraph {
  std::vector<KeyFrameHandle> nodes;                   // every live keyframe
  std::unordered_map<KeyFrameHandle, uint32_t> index;  // node of a keyframe
  std::vector<Similarity3> S;                          // per node: the pose S_cw being optimized
  std::vector<Similarity3> S_before;                   // per node: the pose the points were placed from
  std::vector<bool> fixed;                             // per node: held by the optimization
  PoseGraphEdgeSet edges;

  // Every live keyframe of map at its current pose (S = S_before), none fixed, no edge yet.
  [[nodiscard]] static EssentialGraph OfMap(const Map& map);

  // Adds, for each node, an edge to its spanning-tree parent, its loop edges and the covisible
  // keyframes sharing at least min_covisibility points, measured as measured[i] * measured[j]^-1
  // (measured: per node, the poses the edges are taken from), when keep(i, j) is true.
  void AddMapEdges(const Map& map, const std::vector<Similarity3>& measured, int min_covisibility,
                   const std::function<bool(uint32_t, uint32_t)>& keep);

  // Keyframes take S; each point moves rigidly with the node follow(handle, point) names
  // (from its S_before to its S); a point whose keyframe is not a node stays where it is.
  void Apply(Map* map, const std::function<KeyFrameHandle(PointHandle, const MapPoint&)>& follow) const;
};

}  // namespace flatslam
