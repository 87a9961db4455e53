#include "ecs/map.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <utility>
#include <unordered_map>

#include "core/error.h"

namespace flatslam {

void KeyFrame::resize(size_t n) {
  uv.resize(n, Eigen::Vector2f::Zero());
  right_u.resize(n, -1.0f);
  depth.resize(n, -1.0f);
  angle.resize(n, 0.0f);
  octave.resize(n, 0);
  descriptor.resize(n, Descriptor{});
  points.resize(n, PointHandle::null());
}

KeyFrameHandle Map::AddKeyFrame(KeyFrame&& keyframe) {
  keyframe.id = next_keyframe_id_++;
  FLATSLAM_CHECK(keyframe.points.size() == keyframe.uv.size() && keyframe.descriptor.size() == keyframe.uv.size(),
                 "keyframe columns differ in size");
  return keyframes_.create(std::move(keyframe));
}

KeyFrameHandle Map::RestoreKeyFrame(KeyFrame&& keyframe) {
  FLATSLAM_CHECK(keyframe.points.size() == keyframe.uv.size() && keyframe.descriptor.size() == keyframe.uv.size(),
                 "keyframe columns differ in size");
  const uint64_t id = keyframe.id;
  const KeyFrameHandle h = keyframes_.create(std::move(keyframe));
  next_keyframe_id_ = std::max(next_keyframe_id_, id + 1);
  return h;
}

PointHandle Map::AddPoint(const Eigen::Vector3d& position, KeyFrameHandle reference) {
  MapPoint p;
  p.position = position;
  p.reference = reference;
  if (const KeyFrame* kf = keyframes_.try_get(reference)) p.first_keyframe_id = kf->id;
  return points_.create(std::move(p));
}

void Map::AddObservation(PointHandle p, KeyFrameHandle kf, uint32_t keypoint) {
  MapPoint& point = points_.get(p);
  KeyFrame& frame = keyframes_.get(kf);
  FLATSLAM_CHECK(keypoint < frame.size(), "keypoint ", keypoint, " out of range for ", kf);
  FLATSLAM_CHECK(frame.points[keypoint].is_null(), "keypoint ", keypoint, " of ", kf, " already bound");
  for (const Observation& o : point.observations) FLATSLAM_CHECK(o.keyframe != kf, p, " already observed by ", kf);
  frame.points[keypoint] = p;
  point.observations.push_back({kf, keypoint});
  point.descriptor_stale = true;
}

bool Map::EraseObservation(PointHandle p, KeyFrameHandle kf, size_t min_observations) {
  MapPoint* point = points_.try_get(p);
  if (!point) return false;
  auto it = std::find_if(point->observations.begin(), point->observations.end(),
                         [&](const Observation& o) { return o.keyframe == kf; });
  if (it == point->observations.end()) return false;
  if (KeyFrame* frame = keyframes_.try_get(kf)) frame->points[it->keypoint] = PointHandle::null();
  point->observations.erase(it);
  point->descriptor_stale = true;
  if (point->reference == kf && !point->observations.empty()) point->reference = point->observations.front().keyframe;
  if (point->observations.size() < min_observations) {
    ErasePoint(p);
    return true;
  }
  return false;
}

void Map::ErasePoint(PointHandle p) {
  MapPoint* point = points_.try_get(p);
  if (!point) return;
  for (const Observation& o : point->observations) {
    if (KeyFrame* frame = keyframes_.try_get(o.keyframe)) {
      if (frame->points[o.keypoint] == p) frame->points[o.keypoint] = PointHandle::null();
    }
  }
  points_.erase(p);
}

void Map::RemoveCovisibilityLinks(KeyFrameHandle kf) {
  KeyFrame& frame = keyframes_.get(kf);
  for (const auto& [other, weight] : frame.covisible) {
    if (KeyFrame* o = keyframes_.try_get(other)) {
      std::erase_if(o->covisible, [&](const auto& link) { return link.first == kf; });
    }
  }
  frame.covisible.clear();
}

void Map::EraseKeyFrame(KeyFrameHandle kf) {
  if (!keyframes_.contains(kf)) return;
  {
    // Copy: EraseObservation may erase points, which never touches this keyframe's vector size.
    const std::vector<PointHandle> seen = keyframes_.get(kf).points;
    for (PointHandle p : seen) {
      if (!p.is_null()) EraseObservation(p, kf);
    }
  }
  RemoveCovisibilityLinks(kf);
  KeyFrame& frame = keyframes_.get(kf);
  const KeyFrameHandle parent = frame.parent;
  const std::vector<KeyFrameHandle> children = frame.children;
  // Children move to the erased keyframe's parent (or become roots if it had none).
  for (KeyFrameHandle c : children) {
    if (KeyFrame* child = keyframes_.try_get(c)) {
      child->parent = parent;
      if (KeyFrame* p = keyframes_.try_get(parent)) p->children.push_back(c);
    }
  }
  if (KeyFrame* p = keyframes_.try_get(parent)) std::erase(p->children, kf);
  for (KeyFrameHandle other : frame.loop_edges)
    if (KeyFrame* o = keyframes_.try_get(other)) std::erase(o->loop_edges, kf);
  keyframes_.erase(kf);
}

void Map::ReplacePoint(PointHandle from, PointHandle into) {
  if (from == into || !points_.contains(from) || !points_.contains(into)) return;
  const std::vector<Observation> moved = points_.get(from).observations;
  const uint32_t visible = points_.get(from).visible, found = points_.get(from).found;
  ErasePoint(from);
  MapPoint& keep = points_.get(into);
  keep.visible += visible;
  keep.found += found;
  for (const Observation& o : moved) {
    KeyFrame* frame = keyframes_.try_get(o.keyframe);
    if (!frame) continue;
    const bool already = std::any_of(keep.observations.begin(), keep.observations.end(),
                                     [&](const Observation& k) { return k.keyframe == o.keyframe; });
    if (already || !frame->points[o.keypoint].is_null()) continue;
    frame->points[o.keypoint] = into;
    keep.observations.push_back(o);
    keep.descriptor_stale = true;
  }
}

void Map::BindMatchedPoints(KeyFrameHandle kf, std::span<const PointHandle> matched) {
  for (uint32_t i = 0; i < matched.size(); ++i) {
    const PointHandle p = matched[i];
    if (!points_.contains(p)) continue;
    const PointHandle mine = keyframes_.get(kf).points[i];
    if (mine == p) continue;
    if (points_.contains(mine)) {
      ReplacePoint(mine, p);
    } else {
      const auto& obs = points_.get(p).observations;
      if (std::none_of(obs.begin(), obs.end(), [&](const Observation& o) { return o.keyframe == kf; }))
        AddObservation(p, kf, i);
    }
  }
}

Eigen::Isometry3d MovedCameraPose(const Eigen::Isometry3d& T_cam_world, const Eigen::Isometry3d& T_new_old,
                                  double scale) {
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  out.linear() = T_cam_world.linear() * T_new_old.linear().transpose();
  out.translation() = scale * T_cam_world.translation() - out.linear() * T_new_old.translation();
  return out;
}

void Map::MoveFrame(const Eigen::Isometry3d& T_new_old, double scale) {
  for (KeyFrame& kf : keyframes_.values()) kf.T_cam_world = MovedCameraPose(kf.T_cam_world, T_new_old, scale);
  for (MapPoint& point : points_.values()) {
    point.position = T_new_old.linear() * (scale * point.position) + T_new_old.translation();
    point.normal = T_new_old.linear() * point.normal;
    point.min_distance = static_cast<float>(point.min_distance * scale);
    point.max_distance = static_cast<float>(point.max_distance * scale);
  }
}

void Map::AddLoopEdge(KeyFrameHandle a, KeyFrameHandle b) {
  FLATSLAM_CHECK(a != b, "loop edge from ", a, " to itself");
  KeyFrame& ka = keyframes_.get(a);
  KeyFrame& kb = keyframes_.get(b);
  if (std::find(ka.loop_edges.begin(), ka.loop_edges.end(), b) != ka.loop_edges.end()) return;
  ka.loop_edges.push_back(b);
  kb.loop_edges.push_back(a);
}

void Map::UpdateCovisibility(KeyFrameHandle kf, int min_shared) {
  SetCovisibility(kf, ComputeCovisibility(kf, min_shared));
}

Map::CovisibilityLinks Map::ComputeCovisibility(KeyFrameHandle kf, int min_shared) const {
  // Shared points counted per keyframe slot (live keyframes only, so a slot holds one handle):
  // a keyframe's points reach a few hundred others through some ten thousand observations.
  // Scratch per thread, as callers compute several keyframes' links in parallel; the counts are
  // left at zero after each call.
  thread_local std::vector<int> count_of_slot;
  thread_local std::vector<KeyFrameHandle> others;
  if (count_of_slot.size() < keyframes_.slot_count()) count_of_slot.resize(keyframes_.slot_count(), 0);
  others.clear();
  const KeyFrame& frame = keyframes_.get(kf);
  for (PointHandle p : frame.points) {
    const MapPoint* point = points_.try_get(p);
    if (!point) continue;
    for (const Observation& o : point->observations) {
      if (o.keyframe == kf || !keyframes_.contains(o.keyframe)) continue;
      if (count_of_slot[o.keyframe.index()]++ == 0) others.push_back(o.keyframe);
    }
  }
  CovisibilityLinks links;
  std::pair<KeyFrameHandle, int> best{KeyFrameHandle::null(), 0};
  for (KeyFrameHandle other : others) {
    const int weight = std::exchange(count_of_slot[other.index()], 0);
    const bool better = weight > best.second || (weight == best.second && other < best.first);
    if (better) best = {other, weight};
    if (weight >= min_shared) links.emplace_back(other, weight);
  }
  if (links.empty() && !best.first.is_null()) links.push_back(best);
  std::sort(links.begin(), links.end(), StrongerLink);
  return links;
}

void Map::SetCovisibility(KeyFrameHandle kf, CovisibilityLinks links) {
  RemoveCovisibilityLinks(kf);
  for (const auto& [other, weight] : links) {
    CovisibilityLinks& list = keyframes_.get(other).covisible;
    const std::pair<KeyFrameHandle, int> link(kf, weight);
    list.insert(std::upper_bound(list.begin(), list.end(), link, StrongerLink), link);
  }
  KeyFrame& self = keyframes_.get(kf);
  self.covisible = std::move(links);
  if (self.parent.is_null() && !self.covisible.empty()) {
    // A new keyframe hangs below its strongest neighbour, unless that would close a cycle:
    // neighbours created before it are never its descendants.
    const KeyFrameHandle parent = self.covisible.front().first;
    if (keyframes_.get(parent).id < self.id) {
      self.parent = parent;
      keyframes_.get(parent).children.push_back(kf);
    }
  }
}

std::vector<KeyFrameHandle> Map::BestCovisible(KeyFrameHandle kf, size_t n) const {
  std::vector<KeyFrameHandle> out;
  const KeyFrame* frame = keyframes_.try_get(kf);
  if (!frame) return out;
  for (const auto& [other, weight] : frame->covisible) {
    if (out.size() >= n) break;
    if (keyframes_.contains(other)) out.push_back(other);
  }
  return out;
}

void Map::UpdatePointStats(PointHandle p, const MapScales& scales) {
  MapPoint& point = points_.get(p);
  if (point.observations.empty()) return;
  Eigen::Vector3d normal = Eigen::Vector3d::Zero();
  // Buffers reused across calls: local mapping updates thousands of points per keyframe.
  thread_local std::vector<const Descriptor*> descriptors;
  thread_local std::vector<int> distances, row;
  descriptors.clear();
  for (const Observation& o : point.observations) {
    const KeyFrame& frame = keyframes_.get(o.keyframe);
    normal += (point.position - frame.camera_center()).normalized();
    descriptors.push_back(&frame.descriptor[o.keypoint]);
  }
  point.normal = normal.normalized();

  // Distance range from the reference observation: the point can be matched at any level.
  const KeyFrame* ref = keyframes_.try_get(point.reference);
  const Observation* ref_obs = nullptr;
  for (const Observation& o : point.observations)
    if (o.keyframe == point.reference) ref_obs = &o;
  if (!ref || !ref_obs) {
    ref = &keyframes_.get(point.observations.front().keyframe);
    ref_obs = &point.observations.front();
  }
  const float distance = static_cast<float>((point.position - ref->camera_center()).norm());
  const int level = ref->octave[ref_obs->keypoint];
  const float level_scale = std::pow(scales.scale_factor, static_cast<float>(level));
  point.max_distance = distance * level_scale;
  point.min_distance = point.max_distance / std::pow(scales.scale_factor, static_cast<float>(scales.levels - 1));

  // Representative descriptor: least median distance to the others, chosen again only when the
  // observations changed (after a bundle adjustment only the position did). Distances are
  // symmetric: each pair is measured once.
  if (!point.descriptor_stale) return;
  point.descriptor_stale = false;
  const size_t n = descriptors.size();
  distances.resize(n * n);
  for (size_t i = 0; i < n; ++i) {
    distances[i * n + i] = 0;
    for (size_t j = i + 1; j < n; ++j)
      distances[i * n + j] = distances[j * n + i] = DescriptorDistance(*descriptors[i], *descriptors[j]);
  }
  int best_median = 1 << 30;
  row.resize(n);
  const size_t k = (n - 1) / 2;
  for (size_t i = 0; i < n; ++i) {
    std::copy_n(distances.begin() + static_cast<std::ptrdiff_t>(i * n), n, row.begin());
    // The median beats the best so far only if more than k distances lie below it: counting them
    // is cheaper than selecting the median, and skips most candidates of a long-seen point.
    size_t below = 0;
    for (int d : row) below += d < best_median;
    if (below <= k) continue;
    std::nth_element(row.begin(), row.begin() + static_cast<std::ptrdiff_t>(k), row.end());
    const int median = row[k];
    if (median < best_median) {
      best_median = median;
      point.descriptor = *descriptors[i];
    }
  }
}

std::string Map::Validate() const {
  std::ostringstream problem;
  const auto kf_handles = keyframes_.handles();
  const auto kf_values = keyframes_.values();
  for (size_t i = 0; i < kf_values.size(); ++i) {
    const KeyFrame& kf = kf_values[i];
    const KeyFrameHandle h = kf_handles[i];
    for (uint32_t k = 0; k < kf.points.size(); ++k) {
      const PointHandle p = kf.points[k];
      if (p.is_null()) continue;
      const MapPoint* point = points_.try_get(p);
      if (!point) return (problem << h << " keypoint " << k << " refers to erased " << p, problem.str());
      const bool back = std::any_of(point->observations.begin(), point->observations.end(),
                                    [&](const Observation& o) { return o.keyframe == h && o.keypoint == k; });
      if (!back) return (problem << p << " lacks the observation " << h << "/" << k, problem.str());
    }
    for (const auto& [other, w] : kf.covisible) {
      const KeyFrame* o = keyframes_.try_get(other);
      if (!o) return (problem << h << " covisible with erased " << other, problem.str());
      // Lists are kept sorted by StrongerLink: a binary search finds the mirror; the scan decides
      // only when it does not (an unsorted list).
      const std::pair<KeyFrameHandle, int> mirror(h, w);
      const bool mirrored =
          std::binary_search(o->covisible.begin(), o->covisible.end(), mirror, StrongerLink) ||
          std::any_of(o->covisible.begin(), o->covisible.end(), [&](const auto& l) { return l == mirror; });
      if (!mirrored) return (problem << "covisibility " << h << "-" << other << " not mirrored", problem.str());
    }
    for (KeyFrameHandle other : kf.loop_edges) {
      const KeyFrame* o = keyframes_.try_get(other);
      if (!o) return (problem << h << " has a loop edge to erased " << other, problem.str());
      if (std::find(o->loop_edges.begin(), o->loop_edges.end(), h) == o->loop_edges.end())
        return (problem << "loop edge " << h << "-" << other << " not mirrored", problem.str());
    }
    if (!kf.parent.is_null()) {
      const KeyFrame* parent = keyframes_.try_get(kf.parent);
      if (!parent) return (problem << h << " has erased parent " << kf.parent, problem.str());
      if (std::find(parent->children.begin(), parent->children.end(), h) == parent->children.end())
        return (problem << h << " missing from its parent's children", problem.str());
    }
  }
  const auto p_handles = points_.handles();
  const auto p_values = points_.values();
  for (size_t i = 0; i < p_values.size(); ++i) {
    for (const Observation& o : p_values[i].observations) {
      const KeyFrame* kf = keyframes_.try_get(o.keyframe);
      if (!kf) return (problem << p_handles[i] << " observed by erased " << o.keyframe, problem.str());
      if (o.keypoint >= kf->size() || kf->points[o.keypoint] != p_handles[i])
        return (problem << p_handles[i] << " observation " << o.keyframe << "/" << o.keypoint << " not mirrored",
                problem.str());
    }
  }
  return {};
}

void Map::AssignForSnapshot(const Map& other) {
  keyframes_.assign_from(other.keyframes_, [](KeyFrame& dst, const KeyFrame& src) {
    // The per-keypoint columns are shared, not copied (SharedColumn).
    dst.uv = src.uv;
    dst.right_u = src.right_u;
    dst.depth = src.depth;
    dst.angle = src.angle;
    dst.octave = src.octave;
    dst.descriptor = src.descriptor;
    dst.id = src.id;
    dst.frame_index = src.frame_index;
    dst.t_ns = src.t_ns;
    dst.T_cam_world = src.T_cam_world;
    dst.points = src.points;
    dst.covisible = src.covisible;
    dst.parent = src.parent;
    dst.children = src.children;
    dst.loop_edges = src.loop_edges;
    dst.bow.clear();
    dst.bow_features.clear();
    dst.agent = src.agent;
  });
  points_ = other.points_;
  next_keyframe_id_ = other.next_keyframe_id_;
}

}  // namespace flatslam
