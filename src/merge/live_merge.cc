#include "merge/live_merge.h"

#include <algorithm>
#include <chrono>
#include <map>
#include <optional>

#include "core/clock.h"
#include "core/error.h"
#include "merge/merged_loops.h"
#include "optimization/pose_optimizer.h"
#include "place/vocabulary.h"

namespace flatslam {
namespace {

// Points of the merged map a new keyframe must see to be placed by them (else its run's frame
// places it): well above the 6 unknowns of a pose, as tracking asks of a frame.
constexpr size_t kMinPlacingPoints = 30;

// The keyframes of `map` that query in a search (see GrowingMerge::SearchRunsApart): all of them
// when it was never searched, else those newer than `through` with the `window` before them.
std::vector<KeyFrameHandle> QueryWindow(const Map& map, std::optional<uint64_t> through, size_t window) {
  std::vector<KeyFrameHandle> order(map.keyframes().handles().begin(), map.keyframes().handles().end());
  std::sort(order.begin(), order.end(),
            [&](KeyFrameHandle a, KeyFrameHandle b) { return map.keyframe(a).id < map.keyframe(b).id; });
  if (!through) return order;
  const auto first_new =
      std::find_if(order.begin(), order.end(), [&](KeyFrameHandle h) { return map.keyframe(h).id > *through; });
  if (first_new == order.end()) return {};
  const size_t first = static_cast<size_t>(first_new - order.begin());
  return {order.begin() + static_cast<std::ptrdiff_t>(first - std::min(window, first)), order.end()};
}

// The newest keyframe id of a map (none when it has no keyframe).
std::optional<uint64_t> NewestId(const Map& map) {
  std::optional<uint64_t> newest;
  for (const KeyFrame& kf : map.keyframes().values()) newest = std::max(newest.value_or(kf.id), kf.id);
  return newest;
}

}  // namespace

RunSightings SightingsOf(const Map& map, const AgentMaps::Ids& ids) {
  RunSightings out;
  for (const auto& [id, h] : ids.keyframes)
    if (map.keyframes().contains(h)) out.keyframes.emplace(id, map.keyframe(h).t_ns);
  for (const auto& [id, p] : ids.points) {
    if (!map.points().contains(p)) continue;
    std::vector<std::pair<int64_t, uint32_t>>& seen = out.points[id];
    for (const Observation& o : map.point(p).observations) seen.emplace_back(map.keyframe(o.keyframe).t_ns, o.keypoint);
  }
  return out;
}

GrowingMerge::GrowingMerge(MultiMapMerge merged, std::vector<Run> runs, const std::vector<RunSightings>& sightings,
                           std::vector<KeyFramePoses> poses, const MergeCamera& camera, const MapMergeOptions& options,
                           size_t newest)
    : merged_(std::move(merged)),
      runs_(std::move(runs)),
      index_(runs_.size()),
      poses_(std::move(poses)),
      frames_(runs_.size()),
      camera_(camera),
      options_(options),
      context_(MergedMapContext(camera)),
      newest_(newest) {
  FLATSLAM_CHECK(sightings.size() == runs_.size() && poses_.size() == runs_.size(),
                 "growing merge: one sighting table and one pose table per run");
  for (size_t g = 0; g < merged_.maps.size(); ++g) {
    const Map& map = merged_.maps[g];
    // A run's keyframe is found by agent and timestamp (a timestamp two runs of one agent share
    // in one map is ambiguous and left out, as in FitRunFrames).
    std::map<std::pair<uint32_t, int64_t>, KeyFrameHandle> by_time;
    for (KeyFrameHandle h : map.keyframes().handles()) {
      const KeyFrame& kf = map.keyframe(h);
      auto [it, inserted] = by_time.try_emplace({kf.agent, kf.t_ns}, h);
      if (!inserted) it->second = KeyFrameHandle::null();
    }
    auto find = [&](uint32_t agent, int64_t t_ns) {
      const auto it = by_time.find({agent, t_ns});
      return it == by_time.end() ? KeyFrameHandle::null() : it->second;
    };
    for (size_t r : merged_.members[g]) {
      const uint32_t agent = runs_[r].first;
      RunIndex& index = index_[r];
      for (const auto& [id, t_ns] : sightings[r].keyframes)
        if (const KeyFrameHandle h = find(agent, t_ns); !h.is_null()) index.keyframes.emplace(id, h);
      // A point is where a keyframe that saw it binds the same keypoint now (the merge may have
      // fused it into another point, which the binding follows).
      for (const auto& [id, seen] : sightings[r].points) {
        for (const auto& [t_ns, keypoint] : seen) {
          const KeyFrameHandle h = find(agent, t_ns);
          if (h.is_null()) continue;
          const PointHandle p = map.keyframe(h).points[keypoint];
          if (p.is_null() || !map.points().contains(p)) continue;
          index.points.emplace(id, p);
          break;
        }
      }
    }
  }
  // The full merge searched every keyframe of every map against every other.
  for (const Map& map : merged_.maps) merged_searched_.push_back(NewestId(map));
  Fit();
}

std::vector<GrowingMerge::Run> GrowingMerge::Uncovered(const std::vector<Run>& runs) const {
  std::vector<Run> out;
  for (const Run& run : runs) {
    const auto it = std::find(runs_.begin(), runs_.end(), run);
    if (it == runs_.end() || !frames_[static_cast<size_t>(it - runs_.begin())]) out.push_back(run);
  }
  return out;
}

GrowingMerge::ApartSearch GrowingMerge::SearchRunsApart(const std::vector<Run>& runs, const std::vector<Map>& others,
                                                        const Vocabulary& vocabulary) {
  FLATSLAM_CHECK(runs.size() == others.size(), "search of runs apart: one run per map (", runs.size(), " runs, ",
                 others.size(), " maps)");
  ApartSearch out;
  const size_t window = kSearchWindow * static_cast<size_t>(options_.min_consistent_pairs);
  std::vector<std::vector<KeyFrameHandle>> apart_queries(others.size()), merged_queries(merged_.maps.size());
  for (size_t i = 0; i < others.size(); ++i) {
    const auto mark = apart_searched_.find(runs[i]);
    apart_queries[i] = QueryWindow(
        others[i], mark == apart_searched_.end() ? std::nullopt : std::optional<uint64_t>(mark->second), window);
    out.keyframes += others[i].keyframes().size();
  }
  for (size_t g = 0; g < merged_.maps.size(); ++g) {
    if (merged_.members[g].size() < 2) continue;
    merged_queries[g] = QueryWindow(merged_.maps[g], merged_searched_[g], window);
  }
  // One direction of a pair of maps: `from`'s queries (all: every keyframe) against `into`'s
  // keyframe database.
  auto search = [&](const Map& into, const Map& from, std::span<const KeyFrameHandle> queries, bool all) {
    if ((queries.empty() && !all) || into.keyframes().size() == 0 || from.keyframes().size() == 0) return false;
    const MapOverlap overlap = FindMapOverlap(into, from, vocabulary, camera_, options_, queries);
    out.queries += overlap.queries;
    return overlap.found;
  };
  // A pair of maps: every keyframe of one querying the other's database checks every pair of their
  // keyframes, each side's window querying the other checks every pair with a new keyframe; the
  // cheaper of the three, in queries.
  auto search_pair = [&](const Map& a, const std::vector<KeyFrameHandle>& qa, const Map& b,
                         const std::vector<KeyFrameHandle>& qb) {
    const size_t windows = qa.size() + qb.size(), na = a.keyframes().size(), nb = b.keyframes().size();
    if (nb <= windows && nb <= na) return search(a, b, {}, true);
    if (na <= windows) return search(b, a, {}, true);
    return search(a, b, qb, false) || search(b, a, qa, false);
  };
  for (size_t i = 0; i < others.size() && !out.found; ++i) {
    for (size_t g = 0; g < merged_.maps.size() && !out.found; ++g)
      if (merged_.members[g].size() > 1)
        out.found = search_pair(merged_.maps[g], merged_queries[g], others[i], apart_queries[i]);
    for (size_t j = i + 1; j < others.size() && !out.found; ++j)
      out.found = search_pair(others[i], apart_queries[i], others[j], apart_queries[j]);
  }
  if (!out.found) {
    for (size_t i = 0; i < others.size(); ++i)
      if (const auto newest = NewestId(others[i])) apart_searched_[runs[i]] = *newest;
    for (size_t g = 0; g < merged_.maps.size(); ++g) merged_searched_[g] = NewestId(merged_.maps[g]);
  }
  return out;
}

size_t GrowingMerge::keyframes() const {
  size_t n = 0;
  for (const Map& map : merged_.maps) n += map.keyframes().size();
  return n;
}

void GrowingMerge::Fit() {
  std::vector<uint32_t> agents;
  for (const Run& run : runs_) agents.push_back(run.first);
  frames_ = FitRunFrames(merged_, agents, poses_, !camera_.monocular, newest_);
}

KeyFrameHandle GrowingMerge::AddKeyFrame(const KeyFrameMessage& message, size_t r, const Vocabulary& vocabulary,
                                         GrowReport* report, std::vector<PointHandle>* touched) {
  RunIndex& index = index_[r];
  const RunFrame& frame = *frames_[r];
  Map& map = merged_.maps[frame.output];
  const Similarity3& S = frame.S_output_input;
  const KeyFrame& sent = message.keyframe;
  // The points the merged map holds already, by the agent's ids.
  std::vector<PointHandle> joined(sent.size(), PointHandle::null());
  std::vector<PoseObservation> observations;
  for (uint32_t k = 0; k < sent.size(); ++k) {
    const uint32_t i = message.keypoint_point[k];
    if (i == KeyFrameMessage::kNoPoint) continue;
    const auto found = index.points.find(message.point_ids[i]);
    if (found == index.points.end() || !map.points().contains(found->second)) continue;
    joined[k] = found->second;
    const Eigen::Vector2f uv = sent.uv[k];
    observations.push_back({map.point(found->second).position, uv.cast<double>(), -1,
                            camera_.geometry.pyramid.inv_sigma2[sent.octave[k]]});
  }
  KeyFrame columns = MovedKeyFrameColumns(sent, S);
  // The keyframe goes where those points put it (pose optimization, as tracking places a frame),
  // from where the run's frame puts it: the run's frame is fitted on keyframes the agent may
  // have moved since, and the merged map may have moved its own copies of them.
  if (observations.size() >= kMinPlacingPoints) {
    const PoseOptimizationResult placed =
        OptimizePose(camera_.geometry.camera, 0, columns.T_cam_world, observations, PoseOptimizerOptions{});
    if (placed.success && placed.num_inliers >= static_cast<int>(kMinPlacingPoints)) {
      columns.T_cam_world = placed.T_cam_world;
      ++report->placed_by_points;
    }
  }
  columns.agent = message.agent;
  columns.bow.clear();
  columns.bow_features.clear();
  vocabulary.Transform(columns.descriptor, &columns.bow, &columns.bow_features);
  const Eigen::Isometry3d T_world_cam = columns.T_cam_world.inverse();
  const KeyFrameHandle kf = map.AddKeyFrame(std::move(columns));
  index.keyframes.emplace(sent.id, kf);
  for (uint32_t k = 0; k < sent.size(); ++k) {
    const uint32_t i = message.keypoint_point[k];
    if (i == KeyFrameMessage::kNoPoint) continue;
    PointHandle p = joined[k];
    if (p.is_null()) {
      // A new point where this keyframe sees it (in the merged map's units).
      const Eigen::Vector3d X_cam = S.s * (sent.T_cam_world * message.positions[i]);
      p = map.AddPoint(T_world_cam * X_cam, kf);
      index.points[message.point_ids[i]] = p;
    }
    // Two keypoints of one keyframe on one point (a fuse in the merged map): the first stays.
    const auto& seen = map.point(p).observations;
    if (std::any_of(seen.begin(), seen.end(), [&](const Observation& o) { return o.keyframe == kf; })) continue;
    map.AddObservation(p, kf, k);
    touched->push_back(p);
  }
  return kf;
}

GrowReport GrowingMerge::Grow(const std::vector<KeyFrameMessage>& messages, const Vocabulary& vocabulary) {
  GrowReport report;
  auto start = std::chrono::steady_clock::now();
  std::vector<std::vector<KeyFrameHandle>> added(merged_.maps.size());
  std::vector<std::vector<PointHandle>> touched(merged_.maps.size());
  for (const KeyFrameMessage& message : messages) {
    const auto run = std::find(runs_.begin(), runs_.end(), Run{message.agent, message.session});
    const size_t r = static_cast<size_t>(run - runs_.begin());
    if (run == runs_.end() || !frames_[r]) {
      ++report.skipped;
      continue;
    }
    poses_[r][message.keyframe.t_ns] = message.keyframe.T_cam_world.inverse();
    if (index_[r].keyframes.count(message.keyframe.id)) {
      ++report.updated;
      continue;
    }
    const size_t g = frames_[r]->output;
    added[g].push_back(AddKeyFrame(message, r, vocabulary, &report, &touched[g]));
    ++report.added;
  }
  for (size_t g = 0; g < merged_.maps.size(); ++g) {
    Map& map = merged_.maps[g];
    for (KeyFrameHandle kf : added[g]) map.UpdateCovisibility(kf);
    std::sort(touched[g].begin(), touched[g].end());
    touched[g].erase(std::unique(touched[g].begin(), touched[g].end()), touched[g].end());
  }
  report.join_ms = MsSince(start);

  // The weld around the new keyframes, newest first, each with its best covisible neighbours.
  start = std::chrono::steady_clock::now();
  for (size_t g = 0; g < merged_.maps.size(); ++g) {
    if (added[g].empty()) continue;
    Map& map = merged_.maps[g];
    std::vector<SeamPair> around;
    for (auto it = added[g].rbegin(); it != added[g].rend(); ++it) around.push_back({*it, *it});
    std::vector<KeyFrameHandle> free =
        SelectWeldWindow(map, around, options_.weld_neighbours, options_.max_weld_keyframes);
    // Every new keyframe is free, however many came since the last growth.
    for (KeyFrameHandle kf : added[g])
      if (std::find(free.begin(), free.end(), kf) == free.end()) free.push_back(kf);
    report.welded_keyframes += free.size();
    report.weld_outliers +=
        WeldBundleAdjustment(map, camera_, options_.bundle_adjustment, std::move(free), KeyFrameHandle::null());
    // The points' statistics once, as the weld left them (loop closing reads them).
    for (PointHandle p : touched[g])
      if (map.points().contains(p)) map.UpdatePointStats(p, camera_.scales);
  }
  report.weld_ms = MsSince(start);

  start = std::chrono::steady_clock::now();
  for (size_t g = 0; g < merged_.maps.size() && g < merged_.loop_closers.size(); ++g) {
    if (added[g].empty()) continue;
    MergedMapLoops loops;
    merged_.loop_closers[g].Replay(merged_.maps[g], ReplayOrder(merged_.maps[g], added[g]), context_,
                                   options_.adjust_after_loops, &loops);
    report.loops.insert(report.loops.end(), loops.closures.begin(), loops.closures.end());
  }
  report.loops_ms = MsSince(start);

  start = std::chrono::steady_clock::now();
  Fit();
  report.fit_ms = MsSince(start);
  return report;
}

}  // namespace flatslam
