#include "place/loop_closing.h"

#include <algorithm>
#include <chrono>
#include <unordered_map>
#include <unordered_set>

#include "core/clock.h"
#include "mapping/essential_graph.h"
#include "matching/matcher.h"
#include "place/vocabulary.h"

namespace flatslam {

std::optional<LoopMatch> DetectLoop(const Map& map, KeyFrameDatabase& database, LoopClosingState& state,
                                    const SystemContext& context, KeyFrameHandle current, bool search) {
  const SlamOptions& options = context.options;
  const KeyFrame* kf = map.keyframes().try_get(current);
  if (!kf || kf->bow.empty()) return std::nullopt;
  const size_t apart = static_cast<size_t>(options.loop_min_keyframes);
  const bool detect =
      search && map.keyframes().size() > apart && (state.closures.empty() || state.keyframes_since_loop >= apart);
  ++state.keyframes_since_loop;
  std::vector<PlaceCandidate> candidates;
  if (detect) {
    // The loop must score at least as well as the least similar covisible keyframe.
    float min_score = 1;
    for (const auto& [n, w] : kf->covisible)
      if (const KeyFrame* other = map.keyframes().try_get(n))
        min_score = std::min(min_score, Vocabulary::Score(kf->bow, other->bow));
    if (kf->covisible.empty()) min_score = 0;
    candidates = database.DetectLoopCandidates(map, current, min_score);
  }
  database.Add(current, kf->bow);
  if (!detect) return std::nullopt;

  // Temporal consistency: a candidate's covisibility group must overlap groups that earlier
  // keyframes also found, loop_consistency times in a row.
  using ConsistentGroup = LoopClosingState::ConsistentGroup;
  std::vector<ConsistentGroup> next;
  std::vector<KeyFrameHandle> consistent;
  std::vector<bool> extended(state.consistent_groups.size(), false);
  for (const PlaceCandidate& c : candidates) {
    ConsistentGroup group;
    group.keyframes.push_back(c.keyframe);
    for (const auto& [n, w] : map.keyframe(c.keyframe).covisible) group.keyframes.push_back(n);
    std::sort(group.keyframes.begin(), group.keyframes.end());
    bool found = false, enough = false;
    for (size_t g = 0; g < state.consistent_groups.size(); ++g) {
      const auto& previous = state.consistent_groups[g].keyframes;
      const bool overlap = std::any_of(group.keyframes.begin(), group.keyframes.end(), [&](KeyFrameHandle h) {
        return std::binary_search(previous.begin(), previous.end(), h);
      });
      if (!overlap) continue;
      found = true;
      const int count = state.consistent_groups[g].count + 1;
      if (!extended[g]) {
        next.push_back({group.keyframes, count});
        extended[g] = true;
      }
      if (count >= options.loop_consistency) enough = true;
    }
    if (enough) consistent.push_back(c.keyframe);
    if (!found) next.push_back({group.keyframes, 0});
  }
  state.consistent_groups = std::move(next);
  PlaceVerificationOptions verification;
  verification.ransac.fix_scale = !context.monocular();
  for (KeyFrameHandle candidate : consistent) {
    std::optional<PlaceMatch> match = VerifyPlace(map.keyframe(current), map, candidate, map, context.geometry,
                                                  options.matcher, verification, state.rng);
    if (!match || match->matches < options.min_loop_matches) continue;
    LoopMatch loop;
    static_cast<PlaceMatch&>(loop) = std::move(*match);
    loop.candidate = candidate;
    return loop;
  }
  return std::nullopt;
}

void CorrectLoop(Map& map, LoopClosingState& state, const SystemContext& context, KeyFrameHandle current,
                 const LoopMatch& m) {
  const auto start = std::chrono::steady_clock::now();
  const Eigen::Vector3d old_center = map.keyframe(current).camera_center();
  map.UpdateCovisibility(current);

  // 1. The current keyframe and its neighbours move rigidly with the loop correction.
  const uint32_t agent = map.keyframe(current).agent;
  auto held = [&](KeyFrameHandle k) { return state.hold_other_agents && map.keyframe(k).agent != agent; };
  std::vector<KeyFrameHandle> connected = {current};
  for (const auto& [n, w] : map.keyframe(current).covisible)
    if (!held(n)) connected.push_back(n);
  std::unordered_map<KeyFrameHandle, Similarity3> corrected, uncorrected;
  const Eigen::Isometry3d T_world_current = map.keyframe(current).T_cam_world.inverse();
  for (KeyFrameHandle k : connected) {
    const Eigen::Isometry3d T_kw = map.keyframe(k).T_cam_world;
    uncorrected[k] = Similarity3::FromIsometry(T_kw);
    corrected[k] = k == current ? m.S_cw : Similarity3::FromIsometry(T_kw * T_world_current) * m.S_cw;
  }
  std::unordered_map<PointHandle, KeyFrameHandle> corrected_by;
  for (KeyFrameHandle k : connected) {
    for (PointHandle p : map.keyframe(k).points) {
      if (!map.points().contains(p) || corrected_by.count(p)) continue;
      corrected_by[p] = k;
      MapPoint& point = map.point(p);
      point.position = corrected[k].inverse() * (uncorrected[k] * point.position);
    }
  }
  for (KeyFrameHandle k : connected) map.keyframe(k).T_cam_world = corrected[k].ToIsometry();

  // 2. Fuse the loop: the current keyframe takes the loop-side points, its neighbours too.
  map.BindMatchedPoints(current, m.matched);
  for (KeyFrameHandle k : connected)
    if (map.keyframes().contains(k)) FusePoints(map, k, m.nearby, context.geometry, context.options.matcher);

  // 3. New covisibility links across the loop.
  std::unordered_set<KeyFrameHandle> connected_set(connected.begin(), connected.end());
  std::vector<std::pair<KeyFrameHandle, KeyFrameHandle>> loop_links;
  for (KeyFrameHandle k : connected) {
    if (!map.keyframes().contains(k)) continue;
    std::unordered_set<KeyFrameHandle> before;
    for (const auto& [n, w] : map.keyframe(k).covisible) before.insert(n);
    map.UpdateCovisibility(k);
    for (const auto& [n, w] : map.keyframe(k).covisible)
      if (!before.count(n) && !connected_set.count(n)) loop_links.emplace_back(k, n);
  }

  // 4. Essential graph: spanning tree, loop edges, strong covisibility, the new loop links. The
  // connected keyframes already sit at their corrected poses; their edges are measured from the
  // poses before the correction.
  EssentialGraph graph = EssentialGraph::OfMap(map);
  std::vector<Similarity3> measured = graph.S;
  for (uint32_t i = 0; i < graph.nodes.size(); ++i) {
    if (const auto it = uncorrected.find(graph.nodes[i]); it != uncorrected.end()) measured[i] = it->second;
    graph.fixed[i] = graph.nodes[i] == m.candidate || held(graph.nodes[i]);
  }
  for (const auto& [k, n] : loop_links) {
    const uint32_t i = graph.index.at(k), j = graph.index.at(n);
    const auto& cov = map.keyframe(k).covisible;
    const auto w = std::find_if(cov.begin(), cov.end(), [&](const auto& l) { return l.first == n; });
    if (k != current && n != m.candidate &&
        (w == cov.end() || w->second < context.options.essential_graph_min_covisibility))
      continue;
    graph.edges.Add(i, j, graph.S[i] * graph.S[j].inverse());
  }
  graph.AddMapEdges(map, measured, context.options.essential_graph_min_covisibility,
                    [](uint32_t, uint32_t) { return true; });
  {
    const uint32_t i = graph.index.at(current), j = graph.index.at(m.candidate);
    graph.edges.Add(i, j, graph.S[i] * graph.S[j].inverse());
  }
  PoseGraphOptions graph_options;
  graph_options.fix_scale = !context.monocular();
  OptimizePoseGraph(graph.S, graph.fixed, graph.edges.edges(), graph_options);

  // 5. Write back: keyframes take the optimized poses; points follow the keyframe that moved them.
  graph.Apply(&map, [&](PointHandle p, const MapPoint& point) {
    const auto by = corrected_by.find(p);
    return by != corrected_by.end() ? by->second : point.reference;
  });
  for (PointHandle p : map.points().handles()) map.UpdatePointStats(p, context.map_scales);
  map.AddLoopEdge(current, m.candidate);

  LoopClosure closure;
  closure.frame_index = map.keyframe(current).frame_index;
  closure.matched_frame_index = map.keyframe(m.candidate).frame_index;
  closure.t_ns = map.keyframe(current).t_ns;
  closure.matched_t_ns = map.keyframe(m.candidate).t_ns;
  closure.agent = map.keyframe(current).agent;
  closure.matched_agent = map.keyframe(m.candidate).agent;
  closure.matches = m.matches;
  closure.scale = m.S_cw.s;
  closure.correction_m = (map.keyframe(current).camera_center() - old_center).norm();
  closure.correction_ms = MsSince(start);
  state.closures.push_back(closure);
  state.consistent_groups.clear();
  state.keyframes_since_loop = 0;
}

bool BuildGlobalBundleAdjustment(const Map& map, const SystemContext& context, KeyFrameHandle anchor,
                                 MapBundleAdjustment* ba) {
  const auto kfs = map.keyframes().handles();
  if (kfs.empty()) return false;
  // The gauge: the map's first keyframe (never culled), else any one.
  if (!map.keyframes().contains(anchor)) anchor = kfs.front();
  BuildMapBundleAdjustment(map, context.geometry, context.stereo_depth, kfs, anchor, 2, ba);
  return !ba->problem.observations.empty();
}

BundleAdjustmentResult SolveGlobalBundleAdjustment(MapBundleAdjustment& ba, const SystemContext& context,
                                                   std::function<bool()> stop) {
  BundleAdjustmentOptions options = context.options.bundle_adjustment;
  options.linear_solver = BundleAdjustmentOptions::LinearSolver::kSparseSchur;
  options.stop_early = std::move(stop);
  return LocalBundleAdjustment(ba.problem, options);
}

void ApplyGlobalBundleAdjustment(Map& map, const SystemContext& context, const MapBundleAdjustment& ba,
                                 const BundleAdjustmentResult& result) {
  // Keyframes in the solution take it; keyframes made since follow their spanning-tree parent.
  std::unordered_map<KeyFrameHandle, Eigen::Isometry3d> before, after;
  for (size_t k = 0; k < ba.keyframes.size(); ++k) {
    const KeyFrame* kf = map.keyframes().try_get(ba.keyframes[k]);
    if (!kf) continue;
    before[ba.keyframes[k]] = kf->T_cam_world;
    after[ba.keyframes[k]] = ba.problem.poses[k].T_cam_world;
  }
  ApplyMapBundleAdjustment(ba, result, /*erase_outliers=*/false, &map);
  bool progress = true;
  while (progress) {
    progress = false;
    for (KeyFrameHandle h : map.keyframes().handles()) {
      if (after.count(h)) continue;
      KeyFrame& kf = map.keyframe(h);
      const auto parent_before = before.find(kf.parent);
      if (parent_before == before.end()) continue;
      before[h] = kf.T_cam_world;
      kf.T_cam_world = kf.T_cam_world * parent_before->second.inverse() * after.at(kf.parent);
      after[h] = kf.T_cam_world;
      progress = true;
    }
  }
  const std::unordered_set<PointHandle> solved(ba.points.begin(), ba.points.end());
  for (PointHandle p : map.points().handles()) {
    if (solved.count(p)) continue;
    MapPoint& point = map.point(p);
    const auto b = before.find(point.reference);
    if (b == before.end()) continue;
    point.position = after.at(point.reference).inverse() * (b->second * point.position);
  }
  for (PointHandle p : map.points().handles()) map.UpdatePointStats(p, context.map_scales);
}

}  // namespace flatslam
