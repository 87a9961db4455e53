#include "merge_and_save.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include <Eigen/Geometry>

#include "config/options.h"
#include "core/clock.h"
#include "core/error.h"

namespace flatslam::app {

double VirtualBaseline(const SnapshotMetadata& metadata) {
  return metadata.rgbd_virtual_baseline_m > 0 ? metadata.rgbd_virtual_baseline_m
                                              : SlamOptions{}.rgbd_virtual_baseline_m;
}

std::string Agents(const Map& map) {
  std::vector<uint32_t> agents;
  for (const KeyFrame& kf : map.keyframes().values()) agents.push_back(kf.agent);
  std::sort(agents.begin(), agents.end());
  agents.erase(std::unique(agents.begin(), agents.end()), agents.end());
  std::string out;
  for (uint32_t a : agents) out += (out.empty() ? "" : ",") + std::to_string(a);
  return out;
}

MergeTimes MergeAndSave(std::vector<Map> maps, const Vocabulary& vocabulary, const SnapshotMetadata& metadata,
                        const MapMergeOptions& options, const std::filesystem::path& out_path,
                        const std::function<void(const MultiMapMerge&)>& on_merged) {
  const MergeCamera camera =
      MergeCamera::FromCalibration(metadata.calibration, metadata.scales, VirtualBaseline(metadata));
  const auto merge_start = std::chrono::steady_clock::now();
  MultiMapMerge merged = MergeAllMaps(std::move(maps), vocabulary, camera, options);
  const double merge_ms = MsSince(merge_start);
  auto list = [&](const std::vector<size_t>& members) {
    std::string s;
    for (size_t m : members) s += (s.empty() ? "" : "+") + std::to_string(m);
    return s;
  };
  for (const OverlapEdge& e : merged.overlaps) {
    std::printf("overlap       %zu-%zu: %s (%zu independent agreeing pairs, %zu point pairs)\n", e.a, e.b,
                e.found ? "found" : "none", e.independent_pairs, e.correspondences);
  }
  for (const MergeAttempt& a : merged.attempts) {
    const MergeReport& r = a.report;
    const MapOverlap& o = r.overlap;
    std::printf(
        "try           %s into %s: %zu keyframes queried, %zu candidates, %zu pairs verified, %zu agree "
        "(%zu independent), %.0f ms\n",
        list(a.from).c_str(), list(a.into).c_str(), o.queries, o.candidates, o.verified.size(), o.consistent.size(),
        o.independent_pairs, r.place_ms);
    if (!r.merged) {
      std::printf("              no overlap: fewer than %d independent agreeing pairs\n", options.min_consistent_pairs);
      continue;
    }
    const Similarity3& S = o.S_into_from;
    const Eigen::AngleAxisd rotation(S.R);
    std::printf(
        "              transform t [%.3f %.3f %.3f], rotation %.2f deg, scale %.4f (%zu point pairs, "
        "rms %.3f)\n",
        S.t.x(), S.t.y(), S.t.z(), rotation.angle() * 180.0 / M_PI, S.s, o.correspondences, o.residual_rms);
    std::printf(
        "              merged: %zu keyframes and %zu points added, %zu points fused, %zu loop edges, "
        "%zu keyframes welded (%zu outlier observations), %.0f ms (fuse %.0f, essential graph %.0f, "
        "weld %.0f)\n",
        r.keyframes_added, r.points_added, r.points_fused, r.loop_edges, r.welded_keyframes, r.weld_outliers,
        r.merge_ms, r.fuse_ms, r.graph_ms, r.weld_ms);
  }
  for (size_t g = 0; g < merged.adjustments.size(); ++g) {
    const MergedMapAdjustment& a = merged.adjustments[g];
    if (a.keyframes == 0) continue;
    std::printf("adjusted      map %zu: %zu keyframes free%s, %zu outlier observations, %.0f ms\n", g, a.keyframes,
                a.refined ? " (refine: full passes)" : "", a.outliers, a.ms);
  }
  for (size_t g = 0; g < merged.loops.size(); ++g) {
    const MergedMapLoops& loops = merged.loops[g];
    if (loops.keyframes == 0) continue;
    std::printf(
        "loops         map %zu: %zu keyframes searched, %zu loops closed, %.0f ms (%zu global bundle "
        "adjustments after them, %.0f ms)\n",
        g, loops.keyframes, loops.closures.size(), loops.ms, loops.global_adjustments, loops.global_adjustment_ms);
    for (const LoopClosure& c : loops.closures)
      std::printf(
          "              agent %u keyframe at %.2f s to agent %u's at %.2f s: %d points matched, moved %.3f m\n",
          c.agent, c.t_ns * 1e-9, c.matched_agent, c.matched_t_ns * 1e-9, c.matches, c.correction_m);
  }
  if (on_merged) on_merged(merged);
  std::vector<SnapshotMapRef> refs;
  for (size_t g = 0; g < merged.maps.size(); ++g) {
    const std::string problem = merged.maps[g].Validate();
    FLATSLAM_CHECK(problem.empty(), "merged map ", g, " is inconsistent: ", problem);
    refs.push_back({static_cast<uint32_t>(g), &merged.maps[g]});
    std::printf("output map %-3zu inputs %s, agents [%s], %zu keyframes, %zu map points%s\n", g,
                list(merged.members[g]).c_str(), Agents(merged.maps[g]).c_str(), merged.maps[g].keyframes().size(),
                merged.maps[g].points().size(),
                merged.members[g].size() == 1 ? " (overlaps no other map: kept separate, in its own frame)" : "");
  }
  const auto save_start = std::chrono::steady_clock::now();
  SaveMapSnapshot(out_path, refs, metadata);
  const double save_ms = MsSince(save_start);
  std::printf("wrote         %s: %zu map%s (%.2f MiB)\n", out_path.c_str(), refs.size(), refs.size() == 1 ? "" : "s",
              std::filesystem::file_size(out_path) / 1048576.0);
  return MergeTimes{merge_ms, save_ms, refs.size()};
}

}  // namespace flatslam::app
