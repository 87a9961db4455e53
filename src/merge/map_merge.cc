#include "merge/map_merge.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <optional>
#include <random>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <utility>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "core/clock.h"
#include "core/error.h"
#include "config/options.h"
#include "core/requirements.h"
#include "mapping/essential_graph.h"
#include "place/keyframe_database.h"
#include "place/place_verification.h"
#include "slam/session.h"
#include "place/vocabulary.h"

namespace flatslam {

namespace {

double AngleDeg(const Eigen::Matrix3d& R) {
  const double c = std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0);
  return std::acos(c) * 180.0 / M_PI;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

// The camera pose (rigid, T_cam_world) a pose S_cw implies, as a scale-1 similarity.
Similarity3 PoseOf(const Similarity3& S_cw) {
  return Similarity3::FromIsometry(S_cw.ToIsometry());
}

// Map::UpdateCovisibility of every keyframe given (all alive): counted in parallel (reads only),
// then written in one pass.
void UpdateCovisibilities(const std::vector<KeyFrameHandle>& keyframes, Map* map) {
  std::vector<Map::CovisibilityLinks> links(keyframes.size());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, keyframes.size(), 16), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t k = r.begin(); k != r.end(); ++k) links[k] = std::as_const(*map).ComputeCovisibility(keyframes[k]);
  });
  for (size_t k = 0; k < keyframes.size(); ++k) map->SetCovisibility(keyframes[k], std::move(links[k]));
}

// Every point's normal, distance range and descriptor, in parallel: each point's statistics read
// the keyframes and write that point alone.
void UpdateAllPointStats(const MapScales& scales, Map* map) {
  const std::vector<PointHandle> points(map->points().handles().begin(), map->points().handles().end());
  tbb::parallel_for(tbb::blocked_range<size_t>(0, points.size(), 256), [&](const tbb::blocked_range<size_t>& r) {
    for (size_t i = r.begin(); i != r.end(); ++i) map->UpdatePointStats(points[i], scales);
  });
}

// Verifies one place-recognition candidate: bag-of-words matches, RANSAC, guided search.
bool VerifyPair(const Map& into, const Map& from, KeyFrameHandle query, KeyFrameHandle candidate,
                const MergeCamera& camera, const MapMergeOptions& options, std::mt19937_64& rng, MergePair* out) {
  const KeyFrame& q = from.keyframe(query);
  PlaceVerificationOptions verification;
  verification.min_bow_matches = options.min_bow_matches;
  verification.ransac.fix_scale = !camera.monocular;
  verification.ransac.iterations = options.ransac_iterations;
  verification.ransac.min_inliers = std::min(options.min_bow_matches, verification.ransac.min_inliers);
  std::optional<PlaceMatch> match =
      VerifyPlace(q, from, candidate, into, camera.geometry, options.matcher, verification, rng);
  if (!match || match->matches < options.min_matches) return false;
  const Similarity3 S_cw = match->S_cw;
  out->matched = std::move(match->matched);
  out->matches = match->matches;

  out->from_keyframe = query;
  out->into_keyframe = candidate;
  out->S_into_from = S_cw.inverse() * Similarity3::FromIsometry(q.T_cam_world);
  const Eigen::Vector3d center = S_cw.inverse().t;
  std::vector<double> depths;
  for (PointHandle p : out->matched)
    if (!p.is_null()) depths.push_back((into.point(p).position - center).norm());
  out->scene_depth = Median(std::move(depths));
  return true;
}

// Do two pairs see the same transform (up to drift between them)?
bool Agree(const MergePair& a, const MergePair& b, const Map& from, bool monocular, const MapMergeOptions& options) {
  if (AngleDeg(a.S_into_from.R * b.S_into_from.R.transpose()) > options.max_rotation_disagreement_deg) return false;
  if (monocular && std::abs(a.S_into_from.s / b.S_into_from.s - 1.0) > options.max_scale_disagreement) return false;
  const Eigen::Vector3d ca = from.keyframe(a.from_keyframe).camera_center();
  const Eigen::Vector3d cb = from.keyframe(b.from_keyframe).camera_center();
  const double error =
      std::max((a.S_into_from * ca - b.S_into_from * ca).norm(), (a.S_into_from * cb - b.S_into_from * cb).norm());
  const double separation = (a.S_into_from * ca - a.S_into_from * cb).norm();
  const double depth = 0.5 * (a.scene_depth + b.scene_depth);
  return error <= options.max_position_disagreement * depth + options.drift_fraction * separation;
}

// Pairs of a group with distinct keyframes on both sides, strongest first.
size_t IndependentPairs(const std::vector<MergePair>& pairs, const std::vector<size_t>& group) {
  std::vector<size_t> order = group;
  std::sort(order.begin(), order.end(), [&](size_t x, size_t y) { return pairs[x].matches > pairs[y].matches; });
  std::unordered_set<KeyFrameHandle> used_from, used_into;
  size_t count = 0;
  for (size_t k : order) {
    if (used_from.count(pairs[k].from_keyframe) || used_into.count(pairs[k].into_keyframe)) continue;
    used_from.insert(pairs[k].from_keyframe);
    used_into.insert(pairs[k].into_keyframe);
    ++count;
  }
  return count;
}

}  // namespace

MergeCamera MergeCamera::FromCalibration(const Calibration& calibration, const MapScales& scales,
                                         double rgbd_virtual_baseline_m, double far_stereo_baselines) {
  FLATSLAM_CHECK(calibration.sensor != Sensor::kRgbd || rgbd_virtual_baseline_m > 0,
                 "map merge: RGB-D maps need their virtual stereo baseline (got ", rgbd_virtual_baseline_m, ")");
  MergeCamera out;
  out.geometry = CameraGeometry::FromCalibration(calibration, rgbd_virtual_baseline_m,
                                                 ScalePyramid::Make(scales.levels, scales.scale_factor));
  out.scales = scales;
  out.monocular = calibration.sensor == Sensor::kMonocular;
  out.stereo_depth =
      StereoDepthRule::ForRig(calibration.sensor == Sensor::kStereo, calibration.baseline_m, far_stereo_baselines);
  out.calibration = calibration;
  out.rgbd_virtual_baseline_m = rgbd_virtual_baseline_m;
  out.far_stereo_baselines = far_stereo_baselines;
  return out;
}

std::string MapMergeOptions::Problem() const {
  Requirements r;
  r.Nested("matcher", matcher.Problem());
  r.Nested("bundle_adjustment", bundle_adjustment.Problem());
  FLATSLAM_REQUIRE(r, candidates_per_keyframe > 0);
  FLATSLAM_REQUIRE(r, min_bow_matches >= 3);
  FLATSLAM_REQUIRE(r, min_matches >= 3);
  FLATSLAM_REQUIRE(r, min_consistent_pairs >= 1);
  FLATSLAM_REQUIRE(r, max_rotation_disagreement_deg > 0);
  FLATSLAM_REQUIRE(r, max_position_disagreement > 0);
  FLATSLAM_REQUIRE(r, drift_fraction >= 0);
  FLATSLAM_REQUIRE(r, max_scale_disagreement > 0);
  FLATSLAM_REQUIRE(r, ransac_iterations > 0);
  FLATSLAM_REQUIRE(r, pose_graph_iterations >= 0);
  FLATSLAM_REQUIRE(r, adjust_iterations >= 0);
  FLATSLAM_REQUIRE(r, essential_graph_min_covisibility > 0);
  return r.first();
}

void ComputeKeyFrameBow(Map& map, const Vocabulary& vocabulary, bool missing_only) {
  for (KeyFrame& kf : map.keyframes().values()) {
    if (missing_only && !kf.bow.empty()) continue;
    kf.bow.clear();
    kf.bow_features.clear();
    vocabulary.Transform(kf.descriptor, &kf.bow, &kf.bow_features);
  }
}

MapOverlap FindMapOverlap(const Map& into, const Map& from, const Vocabulary& vocabulary, const MergeCamera& camera,
                          const MapMergeOptions& options, std::span<const KeyFrameHandle> only) {
  const std::string problem = options.Problem();
  FLATSLAM_CHECK(problem.empty(), "invalid map merge options: ", problem, " does not hold");
  MapOverlap overlap;
  KeyFrameDatabase database(vocabulary.word_count());
  for (size_t i = 0; i < into.keyframes().size(); ++i) {
    const KeyFrame& kf = into.keyframes().values()[i];
    if (!kf.bow.empty()) database.Add(into.keyframes().handles()[i], kf.bow);
  }
  std::vector<KeyFrameHandle> queries;
  if (only.empty()) {
    for (size_t i = 0; i < from.keyframes().size(); ++i)
      if (!from.keyframes().values()[i].bow.empty()) queries.push_back(from.keyframes().handles()[i]);
  } else {
    for (KeyFrameHandle h : only)
      if (const KeyFrame* kf = from.keyframes().try_get(h); kf && !kf->bow.empty()) queries.push_back(h);
  }
  std::sort(queries.begin(), queries.end(),
            [&](KeyFrameHandle a, KeyFrameHandle b) { return from.keyframe(a).id < from.keyframe(b).id; });
  overlap.queries = queries.size();
  if (database.size() == 0 || queries.empty()) return overlap;

  // Each query is verified on its own (reads only), with its own random stream.
  std::vector<std::vector<MergePair>> found(queries.size());
  std::vector<size_t> checked(queries.size(), 0);
  tbb::parallel_for(tbb::blocked_range<size_t>(0, queries.size(), 4), [&](const tbb::blocked_range<size_t>& range) {
    for (size_t k = range.begin(); k != range.end(); ++k) {
      std::vector<PlaceCandidate> candidates =
          database.DetectRelocalizationCandidates(into, from.keyframe(queries[k]).bow);
      if (candidates.size() > options.candidates_per_keyframe) candidates.resize(options.candidates_per_keyframe);
      std::mt19937_64 rng(options.seed * 0x9E3779B97F4A7C15ull + k);
      for (const PlaceCandidate& c : candidates) {
        ++checked[k];
        MergePair pair;
        if (VerifyPair(into, from, queries[k], c.keyframe, camera, options, rng, &pair))
          found[k].push_back(std::move(pair));
      }
    }
  });
  for (size_t k = 0; k < queries.size(); ++k) {
    overlap.candidates += checked[k];
    for (MergePair& p : found[k]) overlap.verified.push_back(std::move(p));
  }
  const std::vector<MergePair>& verified = overlap.verified;
  if (verified.empty()) return overlap;

  // The largest group of pairs agreeing with one of them, counted in independent pairs.
  size_t best_independent = 0;
  int best_matches = 0;
  for (size_t i = 0; i < verified.size(); ++i) {
    std::vector<size_t> group = {i};
    int matches = verified[i].matches;
    for (size_t j = 0; j < verified.size(); ++j) {
      if (j == i || !Agree(verified[i], verified[j], from, camera.monocular, options)) continue;
      group.push_back(j);
      matches += verified[j].matches;
    }
    const size_t independent = IndependentPairs(verified, group);
    if (independent > best_independent || (independent == best_independent && matches > best_matches)) {
      best_independent = independent;
      best_matches = matches;
      std::sort(group.begin(), group.end());
      overlap.consistent = std::move(group);
    }
  }
  overlap.independent_pairs = best_independent;
  if (static_cast<int>(best_independent) < options.min_consistent_pairs) return overlap;

  // One transform for the whole seam, fitted on the matched points of the agreeing pairs with
  // two rounds of trimming (drift between the pairs shows as residual).
  std::vector<Eigen::Vector3d> X_from, X_into;
  std::unordered_set<uint64_t> seen;
  for (size_t k : overlap.consistent) {
    const MergePair& pair = verified[k];
    const KeyFrame& q = from.keyframe(pair.from_keyframe);
    for (uint32_t i = 0; i < pair.matched.size(); ++i) {
      const PointHandle pi = pair.matched[i], pf = q.points[i];
      if (pi.is_null() || !from.points().contains(pf)) continue;
      if (!seen.insert(pf.packed() * 0x9E3779B97F4A7C15ull ^ pi.packed()).second) continue;
      X_from.push_back(from.point(pf).position);
      X_into.push_back(into.point(pi).position);
    }
  }
  std::optional<Similarity3> S = AlignPoints(X_from, X_into, !camera.monocular);
  if (!S) return overlap;
  for (int round = 0; round < 2; ++round) {
    std::vector<double> residual(X_from.size());
    for (size_t k = 0; k < X_from.size(); ++k) residual[k] = (*S * X_from[k] - X_into[k]).norm();
    const double gate = 3.0 * Median(residual) + 1e-9;
    std::vector<Eigen::Vector3d> keep_from, keep_into;
    for (size_t k = 0; k < X_from.size(); ++k) {
      if (residual[k] > gate) continue;
      keep_from.push_back(X_from[k]);
      keep_into.push_back(X_into[k]);
    }
    const auto refit = AlignPoints(keep_from, keep_into, !camera.monocular);
    if (!refit) break;
    S = refit;
    X_from.swap(keep_from);
    X_into.swap(keep_into);
  }
  double sum2 = 0;
  for (size_t k = 0; k < X_from.size(); ++k) sum2 += (*S * X_from[k] - X_into[k]).squaredNorm();
  overlap.S_into_from = *S;
  overlap.correspondences = X_from.size();
  overlap.residual_rms = X_from.empty() ? 0 : std::sqrt(sum2 / X_from.size());
  overlap.found = true;
  return overlap;
}

KeyFrameHandle MapRemap::operator()(const Map& from, KeyFrameHandle h) const {
  if (!from.keyframes().contains(h)) return KeyFrameHandle::null();
  return keyframes[h.index()];
}

PointHandle MapRemap::operator()(const Map& from, PointHandle h) const {
  if (!from.points().contains(h)) return PointHandle::null();
  return points[h.index()];
}

KeyFrame MovedKeyFrameColumns(const KeyFrame& source, const Similarity3& S_into_from) {
  KeyFrame copy;
  copy.frame_index = source.frame_index;
  copy.t_ns = source.t_ns;
  copy.T_cam_world = (Similarity3::FromIsometry(source.T_cam_world) * S_into_from.inverse()).ToIsometry();
  copy.uv = source.uv;
  copy.right_u = source.right_u;
  copy.depth = source.depth;
  if (const double s = S_into_from.s; s != 1.0) {
    float* depth = copy.depth.mutable_data();
    for (size_t k = 0; k < copy.depth.size(); ++k)
      if (depth[k] > 0) depth[k] = static_cast<float>(depth[k] * s);
  }
  copy.angle = source.angle;
  copy.octave = source.octave;
  copy.descriptor = source.descriptor;
  copy.points.assign(source.size(), PointHandle::null());
  copy.bow = source.bow;
  copy.bow_features = source.bow_features;
  copy.agent = source.agent;
  return copy;
}

MapRemap AppendMap(Map& into, const Map& from, const Similarity3& S_into_from) {
  MapRemap remap;
  remap.keyframes.assign(from.keyframes().slot_count(), KeyFrameHandle::null());
  remap.points.assign(from.points().slot_count(), PointHandle::null());
  const double s = S_into_from.s;

  // Fresh handles first (keyframes in id order, so new ids keep from's order), then every
  // handle-typed field rewritten through the tables.
  std::vector<KeyFrameHandle> order(from.keyframes().handles().begin(), from.keyframes().handles().end());
  std::sort(order.begin(), order.end(),
            [&](KeyFrameHandle a, KeyFrameHandle b) { return from.keyframe(a).id < from.keyframe(b).id; });
  std::unordered_map<uint64_t, uint64_t> new_id;
  into.keyframes().reserve(into.keyframes().size() + order.size());
  into.points().reserve(into.points().size() + from.points().size());
  for (KeyFrameHandle h : order) {
    const KeyFrame& source = from.keyframe(h);
    const KeyFrameHandle added = into.AddKeyFrame(MovedKeyFrameColumns(source, S_into_from));
    remap.keyframes[h.index()] = added;
    new_id[source.id] = into.keyframe(added).id;
  }
  const auto point_handles = from.points().handles();
  const auto point_values = from.points().values();
  for (size_t i = 0; i < point_values.size(); ++i) {
    const MapPoint& source = point_values[i];
    const PointHandle added = into.AddPoint(S_into_from * source.position, remap(from, source.reference));
    remap.points[point_handles[i].index()] = added;
    MapPoint& point = into.point(added);
    point.descriptor = source.descriptor;
    point.normal = S_into_from.R * source.normal;
    point.min_distance = static_cast<float>(source.min_distance * s);
    point.max_distance = static_cast<float>(source.max_distance * s);
    point.visible = source.visible;
    point.found = source.found;
    const auto id = new_id.find(source.first_keyframe_id);
    if (id != new_id.end()) point.first_keyframe_id = id->second;
    point.observations.reserve(source.observations.size());
    for (const Observation& o : source.observations) {
      const KeyFrameHandle kf = remap(from, o.keyframe);
      if (!kf.is_null()) point.observations.push_back({kf, o.keypoint});
    }
  }
  for (KeyFrameHandle h : order) {
    const KeyFrame& source = from.keyframe(h);
    KeyFrame& kf = into.keyframe(remap.keyframes[h.index()]);
    for (size_t k = 0; k < source.size(); ++k) kf.points[k] = remap(from, source.points[k]);
    for (const auto& [other, weight] : source.covisible)
      if (const KeyFrameHandle o = remap(from, other); !o.is_null()) kf.covisible.emplace_back(o, weight);
    // Fresh handles may order ties differently.
    std::sort(kf.covisible.begin(), kf.covisible.end(), Map::StrongerLink);
    kf.parent = remap(from, source.parent);
    for (KeyFrameHandle c : source.children)
      if (const KeyFrameHandle o = remap(from, c); !o.is_null()) kf.children.push_back(o);
    for (KeyFrameHandle l : source.loop_edges)
      if (const KeyFrameHandle o = remap(from, l); !o.is_null()) kf.loop_edges.push_back(o);
  }
  return remap;
}

std::vector<KeyFrameHandle> SelectWeldWindow(const Map& map, std::span<const SeamPair> seam, size_t neighbours,
                                             size_t max_keyframes) {
  std::vector<KeyFrameHandle> window;
  std::unordered_set<KeyFrameHandle> in_window;
  auto add = [&](KeyFrameHandle h) {
    if (map.keyframes().contains(h) && in_window.insert(h).second) window.push_back(h);
  };
  for (const SeamPair& pair : seam) {
    if (window.size() >= max_keyframes) break;
    for (KeyFrameHandle h : {pair.into_keyframe, pair.from_keyframe}) {
      if (!map.keyframes().contains(h)) continue;
      add(h);
      for (KeyFrameHandle n : map.BestCovisible(h, neighbours)) add(n);
    }
  }
  return window;
}

size_t WeldBundleAdjustment(Map& map, const MergeCamera& camera, const BundleAdjustmentOptions& options,
                            std::vector<KeyFrameHandle> free, KeyFrameHandle anchor) {
  size_t outliers = 0;
  MapBundleAdjustment ba;
  BuildMapBundleAdjustment(map, camera.geometry, camera.stereo_depth, free, anchor, 1, &ba);
  if (!ba.problem.observations.empty()) {
    BundleAdjustmentOptions ba_options = options;
    // Beyond the sizes the own solver factorizes (a merged map as a whole), conjugate gradients:
    // memory follows the observations, never a factor's fill.
    if (free.size() > static_cast<size_t>(ba_options.schur_lm_max_poses))
      ba_options.linear_solver = BundleAdjustmentOptions::LinearSolver::kIterativeSchur;
    else if (free.size() > static_cast<size_t>(ba_options.dense_schur_max_poses))
      ba_options.linear_solver = BundleAdjustmentOptions::LinearSolver::kSparseSchur;
    BundleAdjustmentWorkspace workspace;  // both passes reuse the solver's buffers
    const BundleAdjustmentResult result = LocalBundleAdjustment(ba.problem, ba_options, &workspace);
    if (result.success) outliers = ApplyMapBundleAdjustment(ba, result, /*erase_outliers=*/true, &map);
  }
  std::erase_if(free, [&](KeyFrameHandle h) { return !map.keyframes().contains(h); });
  UpdateCovisibilities(free, &map);
  return outliers;
}

MergeReport MergeMaps(Map& into, const Map& from, const Vocabulary& vocabulary, const MergeCamera& camera,
                      const MapMergeOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  MapOverlap overlap = FindMapOverlap(into, from, vocabulary, camera, options);
  const double place_ms = MsSince(start);
  MergeReport report = MergeMaps(into, from, std::move(overlap), camera, options);
  report.place_ms = place_ms;
  return report;
}

MergeReport MergeMaps(Map& into, const Map& from, MapOverlap found, const MergeCamera& camera,
                      const MapMergeOptions& options) {
  MergeReport report;
  report.overlap = std::move(found);
  const auto start = std::chrono::steady_clock::now();
  if (!report.overlap.found) return report;
  const MapOverlap& overlap = report.overlap;
  std::vector<const MergePair*> seam;
  for (size_t k : overlap.consistent) seam.push_back(&overlap.verified[k]);
  std::sort(seam.begin(), seam.end(), [](const MergePair* a, const MergePair* b) { return a->matches > b->matches; });

  // 1. Append: every handle of from gets a fresh local handle.
  std::unordered_set<KeyFrameHandle> original(into.keyframes().handles().begin(), into.keyframes().handles().end());
  KeyFrameHandle anchor;  // into's oldest keyframe holds the frame
  for (KeyFrameHandle h : original)
    if (anchor.is_null() || into.keyframe(h).id < into.keyframe(anchor).id) anchor = h;
  const MapRemap remap = AppendMap(into, from, overlap.S_into_from);
  report.keyframes_added = from.keyframes().size();
  report.points_added = from.points().size();
  auto appended = [&](KeyFrameHandle h) { return !original.count(h); };

  // 2. Join the spanning trees: from's tree is re-rooted at the strongest seam keyframe, which
  // hangs below its match.
  {
    const KeyFrameHandle q = remap(from, seam.front()->from_keyframe), c = seam.front()->into_keyframe;
    std::vector<KeyFrameHandle> path = {q};
    while (!into.keyframe(path.back()).parent.is_null() && path.size() <= from.keyframes().size())
      path.push_back(into.keyframe(path.back()).parent);
    FLATSLAM_CHECK(into.keyframe(path.back()).parent.is_null(),
                   "map merge: the spanning tree of the map merged in has a cycle");
    for (size_t i = path.size() - 1; i >= 1; --i) {
      KeyFrame& upper = into.keyframe(path[i]);
      std::erase(upper.children, path[i - 1]);
      upper.parent = path[i - 1];
      into.keyframe(path[i - 1]).children.push_back(path[i]);
    }
    into.keyframe(q).parent = c;
    into.keyframe(c).children.push_back(q);
  }

  // 3. Fuse: verified matches first, then the seam neighbourhoods searched both ways.
  const size_t points_before = into.points().size();
  std::vector<KeyFrameHandle> seam_into, seam_from;
  std::unordered_set<KeyFrameHandle> seam_set;
  for (const MergePair* pair : seam) {
    const KeyFrameHandle q = remap(from, pair->from_keyframe);
    into.BindMatchedPoints(q, pair->matched);
    into.AddLoopEdge(pair->into_keyframe, q);
    ++report.loop_edges;
    auto add = [&](KeyFrameHandle h, std::vector<KeyFrameHandle>* side) {
      if (into.keyframes().contains(h) && seam_set.insert(h).second) side->push_back(h);
    };
    add(pair->into_keyframe, &seam_into);
    for (KeyFrameHandle n : into.BestCovisible(pair->into_keyframe, options.weld_neighbours)) add(n, &seam_into);
    add(q, &seam_from);
    for (KeyFrameHandle n : into.BestCovisible(q, options.weld_neighbours)) add(n, &seam_from);
  }
  auto points_of = [&](const std::vector<KeyFrameHandle>& keyframes) {
    std::vector<PointHandle> out;
    std::unordered_set<PointHandle> unique;
    for (KeyFrameHandle h : keyframes)
      for (PointHandle p : into.keyframe(h).points)
        if (into.points().contains(p) && unique.insert(p).second) out.push_back(p);
    return out;
  };
  {
    // Each seam keyframe is offered the other side's points that project into its image (found
    // over a copy of the positions: the fuse moves no point), and its matches among them are found
    // for every keyframe in parallel, then applied in order: the map FusePoints would make
    // keyframe by keyframe (see FindFusion).
    struct Side {
      std::vector<PointHandle> points;
      std::vector<Eigen::Vector3d> positions;
    };
    auto side_of = [&](const std::vector<KeyFrameHandle>& keyframes) {
      Side side{points_of(keyframes), {}};
      side.positions.reserve(side.points.size());
      for (PointHandle p : side.points) side.positions.push_back(into.point(p).position);
      return side;
    };
    const Side into_side = side_of(seam_into), from_side = side_of(seam_from);
    std::vector<KeyFrameHandle> order(seam_from);
    order.insert(order.end(), seam_into.begin(), seam_into.end());
    std::vector<std::vector<std::pair<PointHandle, uint32_t>>> matches(order.size());
    tbb::parallel_for(tbb::blocked_range<size_t>(0, order.size(), 2), [&](const tbb::blocked_range<size_t>& r) {
      std::vector<PointHandle> seen;
      for (size_t i = r.begin(); i != r.end(); ++i) {
        const Side& other = i < seam_from.size() ? into_side : from_side;
        const Eigen::Isometry3d T = into.keyframe(order[i]).T_cam_world;
        seen.clear();
        double u, v;
        for (size_t k = 0; k < other.points.size(); ++k)
          if (camera.geometry.Project(T * other.positions[k], &u, &v)) seen.push_back(other.points[k]);
        matches[i] = FindFusion(std::as_const(into), order[i], seen, camera.geometry, options.matcher);
      }
    });
    for (size_t i = 0; i < order.size(); ++i) ApplyFusion(into, order[i], matches[i]);
  }
  report.points_fused = points_before - into.points().size();
  report.fuse_ms = MsSince(start);

  // 4. Covisibility across the seam: every keyframe that sees a seam point.
  {
    std::unordered_set<KeyFrameHandle> touched(seam_set);
    for (PointHandle p : points_of(std::vector<KeyFrameHandle>(seam_set.begin(), seam_set.end())))
      for (const Observation& o : into.point(p).observations) touched.insert(o.keyframe);
    UpdateCovisibilities(std::vector<KeyFrameHandle>(touched.begin(), touched.end()), &into);
  }

  // 5. Welding bundle adjustment: the weld window free (into's oldest held), every other keyframe
  // that sees its points fixed. The poses before it are what step 6 measures the maps' edges from.
  const EssentialGraph before_weld = EssentialGraph::OfMap(into);
  std::unordered_set<KeyFrameHandle> window;
  {
    std::vector<SeamPair> pairs;
    for (const MergePair* pair : seam) pairs.push_back({pair->into_keyframe, remap(from, pair->from_keyframe)});
    const std::vector<KeyFrameHandle> free =
        SelectWeldWindow(into, pairs, options.weld_neighbours, options.max_weld_keyframes);
    window.insert(free.begin(), free.end());
    report.welded_keyframes = free.size();
    report.weld_outliers = WeldBundleAdjustment(into, camera, options.bundle_adjustment, free, anchor);
  }
  report.weld_ms = MsSince(start) - report.fuse_ms;

  // 6. Essential graph over every keyframe merged in, as ORB-SLAM3 ends its merge: into's keyframes
  // hold (its welded window at its welded poses), so the map merged into keeps its shape (its own
  // loops were closed; freeing it lets the seams' tension bend it) and the correction spreads over
  // the map merged in. Spanning tree, loop edges and strong covisibility within that map measured
  // from the poses before the weld, and every seam pair measured by its own transform (so seams in
  // several places bend the map merged in to each of them).
  {
    EssentialGraph graph = EssentialGraph::OfMap(into);
    std::vector<Similarity3> measured(graph.nodes.size());
    for (uint32_t i = 0; i < graph.nodes.size(); ++i) {
      measured[i] = before_weld.S[before_weld.index.at(graph.nodes[i])];
      graph.fixed[i] = !appended(graph.nodes[i]);
    }
    for (const MergePair* pair : seam) {
      const uint32_t i = graph.index.at(pair->into_keyframe), j = graph.index.at(remap(from, pair->from_keyframe));
      const Similarity3 S_q = PoseOf(Similarity3::FromIsometry(from.keyframe(pair->from_keyframe).T_cam_world) *
                                     pair->S_into_from.inverse());
      graph.edges.Add(i, j, measured[i] * S_q.inverse());
    }
    // Across the seam, only the pairs above.
    graph.AddMapEdges(into, measured, options.essential_graph_min_covisibility,
                      [&](uint32_t i, uint32_t j) { return appended(graph.nodes[i]) == appended(graph.nodes[j]); });
    PoseGraphOptions graph_options;
    graph_options.fix_scale = !camera.monocular;
    graph_options.iterations = options.pose_graph_iterations;
    graph_options.num_threads = options.bundle_adjustment.num_threads;
    if (options.pose_graph_iterations > 0) OptimizePoseGraph(graph.S, graph.fixed, graph.edges.edges(), graph_options);
    // A point the weld placed (seen from the window) follows a window keyframe that sees it, one of
    // into's (held: the point stays) before one merged in; any other point follows its keyframe.
    graph.Apply(&into, [&](PointHandle, const MapPoint& point) {
      KeyFrameHandle welded;
      for (const Observation& o : point.observations) {
        if (!window.count(o.keyframe)) continue;
        if (!appended(o.keyframe)) return o.keyframe;
        if (welded.is_null()) welded = o.keyframe;
      }
      if (!welded.is_null()) return welded;
      if (into.keyframes().contains(point.reference) || point.observations.empty()) return point.reference;
      return point.observations.front().keyframe;
    });
  }
  report.graph_ms = MsSince(start) - report.fuse_ms - report.weld_ms;

  UpdateAllPointStats(camera.scales, &into);
  report.merged = true;
  report.merge_ms = MsSince(start);
  return report;
}

std::vector<MergeStep> PlanMergeOrder(size_t count, const std::vector<OverlapEdge>& edges) {
  auto stronger = [&](size_t x, size_t y) {
    const OverlapEdge &ex = edges[x], &ey = edges[y];
    if (ex.independent_pairs != ey.independent_pairs) return ex.independent_pairs > ey.independent_pairs;
    if (ex.correspondences != ey.correspondences) return ex.correspondences > ey.correspondences;
    return x < y;
  };
  // Kruskal: the strongest edges that join two trees.
  std::vector<size_t> order;
  for (size_t e = 0; e < edges.size(); ++e) {
    FLATSLAM_CHECK(edges[e].a < count && edges[e].b < count && edges[e].a != edges[e].b, "PlanMergeOrder: edge ", e,
                   " joins inputs ", edges[e].a, " and ", edges[e].b, " of ", count);
    if (edges[e].found) order.push_back(e);
  }
  std::sort(order.begin(), order.end(), stronger);
  std::vector<size_t> parent(count);
  for (size_t i = 0; i < count; ++i) parent[i] = i;
  auto find = [&](size_t i) {
    while (parent[i] != i) i = parent[i] = parent[parent[i]];
    return i;
  };
  std::vector<size_t> tree;
  for (size_t e : order) {
    const size_t ra = find(edges[e].a), rb = find(edges[e].b);
    if (ra == rb) continue;
    parent[std::max(ra, rb)] = std::min(ra, rb);
    tree.push_back(e);
  }
  // Prim from each tree's lowest input, over the tree's edges.
  std::vector<MergeStep> steps;
  std::vector<bool> joined(count, false);
  for (size_t root = 0; root < count; ++root) {
    if (joined[root]) continue;
    joined[root] = true;
    for (;;) {
      std::optional<size_t> best;
      for (size_t e : tree)
        if (joined[edges[e].a] != joined[edges[e].b] && (!best || stronger(e, *best))) best = e;
      if (!best) break;
      const size_t from = joined[edges[*best].a] ? edges[*best].b : edges[*best].a;
      joined[from] = true;
      steps.push_back({root, from, *best});
    }
  }
  return steps;
}

SystemContext MergedMapContext(const MergeCamera& camera) {
  // Loop closing as a SLAM session runs it, with the default options resolved for the camera.
  SlamOptions slam;
  slam.rgbd_virtual_baseline_m =
      camera.rgbd_virtual_baseline_m > 0 ? camera.rgbd_virtual_baseline_m : slam.rgbd_virtual_baseline_m;
  slam.far_stereo_baselines = camera.far_stereo_baselines;
  return SystemContext(camera.calibration, ResolvedOptions(slam, camera.calibration),
                       ScalePyramid::Make(camera.scales.levels, camera.scales.scale_factor));
}

MergedMapAdjustment AdjustMergedMap(Map& map, const MergeCamera& camera, const MapMergeOptions& options) {
  MergedMapAdjustment out;
  if (options.adjust_iterations == 0 && !options.refine) return out;
  const auto start = std::chrono::steady_clock::now();
  std::vector<KeyFrameHandle> free(map.keyframes().handles().begin(), map.keyframes().handles().end());
  // The lowest id is the oldest keyframe of the first map (keyframes merged in take ids after the
  // map they join): it holds the frame the merged map keeps.
  KeyFrameHandle anchor;
  for (KeyFrameHandle h : free)
    if (anchor.is_null() || map.keyframe(h).id < map.keyframe(anchor).id) anchor = h;
  BundleAdjustmentOptions ba = options.bundle_adjustment;
  if (!options.refine) {
    ba.first_pass_iterations = options.adjust_iterations;
    ba.second_pass_iterations = options.adjust_iterations;
  }
  out.keyframes = free.size();
  out.refined = options.refine;
  out.outliers = WeldBundleAdjustment(map, camera, ba, std::move(free), anchor);
  UpdateAllPointStats(camera.scales, &map);
  out.ms = MsSince(start);
  return out;
}

CameraChange ReexpressMapCamera(Map& map, const RefinedCamera& from, const RefinedCamera& to,
                                const MergeCamera& camera, const MapMergeOptions& options) {
  CameraChange out;
  const PinholeCamera& image = to.camera();
  const std::vector<KeyFrameHandle> keyframes(map.keyframes().handles().begin(), map.keyframes().handles().end());
  std::vector<std::vector<uint32_t>> left(keyframes.size());  // keypoints outside the new image
  std::vector<double> shift(keyframes.size(), 0.0);
  tbb::parallel_for(size_t{0}, keyframes.size(), [&](size_t k) {
    KeyFrame& kf = map.keyframe(keyframes[k]);
    std::vector<Eigen::Vector2d> uv;
    uv.reserve(kf.size());
    for (const Eigen::Vector2f& p : kf.uv) uv.push_back(p.cast<double>());
    const std::vector<Eigen::Vector2d> moved = Reexpress(from, to, uv);
    std::vector<Eigen::Vector2f> column(moved.size());
    for (size_t i = 0; i < moved.size(); ++i) {
      column[i] = moved[i].cast<float>();
      shift[k] = std::max(shift[k], (moved[i] - uv[i]).norm());
      const bool inside = moved[i].x() >= 0 && moved[i].y() >= 0 && moved[i].x() < image.width &&
                          moved[i].y() < image.height;
      if (!inside) left[k].push_back(static_cast<uint32_t>(i));
    }
    kf.uv = std::move(column);
  });
  for (size_t k = 0; k < keyframes.size(); ++k) {
    out.keypoints += map.keyframe(keyframes[k]).size();
    out.max_shift_px = std::max(out.max_shift_px, shift[k]);
    for (uint32_t i : left[k]) {
      const PointHandle p = map.keyframe(keyframes[k]).points[i];
      if (p.is_null()) continue;
      map.EraseObservation(p, keyframes[k]);
      ++out.observations_erased;
    }
  }
  MapMergeOptions adjust = options;
  adjust.refine = true;
  out.adjustment = AdjustMergedMap(map, camera, adjust);
  return out;
}

MapCameraRefinement RefineMapCamera(Map& map, const Calibration& calibration, const MapScales& scales,
                                    const PinholeCamera& given, const CameraRefit& refit, const CameraRefit& more) {
  MapCameraRefinement out;
  out.refit = ThenRefit(refit, more);
  const RefinedCamera from(given, refit), to(given, out.refit);
  out.calibration = calibration;
  out.calibration.camera = to.camera();
  MapMergeOptions options;
  options.bundle_adjustment.num_threads = std::max(1, tbb::this_task_arena::max_concurrency());
  out.change = ReexpressMapCamera(map, from, to, MergeCamera::FromCalibration(out.calibration, scales, 0), options);
  return out;
}

MultiMapMerge MergeAllMaps(std::vector<Map> maps, const Vocabulary& vocabulary, const MergeCamera& camera,
                           const MapMergeOptions& options) {
  MultiMapMerge out;
  for (Map& map : maps) ComputeKeyFrameBow(map, vocabulary, /*missing_only=*/true);
  // The overlap graph: every pair measured once, the lower input as the into side.
  std::vector<MapOverlap> found;
  std::vector<double> place_ms;
  for (size_t a = 0; a < maps.size(); ++a) {
    for (size_t b = a + 1; b < maps.size(); ++b) {
      const auto start = std::chrono::steady_clock::now();
      found.push_back(FindMapOverlap(maps[a], maps[b], vocabulary, camera, options));
      place_ms.push_back(MsSince(start));
      const MapOverlap& o = found.back();
      out.overlaps.push_back({a, b, o.independent_pairs, o.correspondences, o.found});
    }
  }
  std::vector<std::vector<size_t>> members(maps.size());
  for (size_t i = 0; i < maps.size(); ++i) members[i] = {i};
  std::vector<bool> absorbed(maps.size(), false);
  for (const MergeStep& step : PlanMergeOrder(maps.size(), out.overlaps)) {
    MergeAttempt attempt;
    attempt.into = members[step.root];
    attempt.from = members[step.from];
    const OverlapEdge& edge = out.overlaps[step.edge];
    if (members[step.root].size() == 1 && edge.a == step.root && edge.b == step.from) {
      // Both maps are as they were measured: the pair's overlap holds.
      attempt.report = MergeMaps(maps[step.root], maps[step.from], std::move(found[step.edge]), camera, options);
      attempt.report.place_ms = place_ms[step.edge];
    } else {
      attempt.report = MergeMaps(maps[step.root], maps[step.from], vocabulary, camera, options);
    }
    if (attempt.report.merged) {
      members[step.root].insert(members[step.root].end(), members[step.from].begin(), members[step.from].end());
      absorbed[step.from] = true;
      maps[step.from] = Map();
    }
    out.attempts.push_back(std::move(attempt));
  }
  for (size_t i = 0; i < maps.size(); ++i) {
    if (absorbed[i]) continue;
    out.maps.push_back(std::move(maps[i]));
    out.members.push_back(std::move(members[i]));
  }
  if (options.close_loops) {
    const SystemContext context = MergedMapContext(camera);
    out.loops.resize(out.maps.size());
    for (size_t g = 0; g < out.maps.size(); ++g) {
      out.loop_closers.emplace_back(vocabulary, options.seed);
      if (out.members[g].size() > 1)
        out.loops[g] = CloseLoopsInMergedMap(out.maps[g], vocabulary, context, options.seed, &out.loop_closers[g],
                                             options.adjust_after_loops);
    }
  }
  // After the loops: a loop takes out drift an input carried, with the other agents held; freeing
  // every agent before that would spread the drift into them.
  out.adjustments.resize(out.maps.size());
  for (size_t g = 0; g < out.maps.size(); ++g)
    if (out.members[g].size() > 1) out.adjustments[g] = AdjustMergedMap(out.maps[g], camera, options);
  return out;
}

}  // namespace flatslam
