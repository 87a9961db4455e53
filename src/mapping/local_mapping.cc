#include "mapping/local_mapping.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <unordered_set>

#include <tbb/parallel_for.h>

#include "geometry/geometry.h"
#include "matching/matcher.h"

namespace flatslam {
namespace {

// Back-projects a keypoint with depth into the world.
Eigen::Vector3d Unproject(const PinholeCamera& cam, const Eigen::Isometry3d& T_cam_world, const Eigen::Vector2f& uv,
                          float depth) {
  const Eigen::Vector3d Xc((uv.x() - cam.cx) / cam.fx * depth, (uv.y() - cam.cy) / cam.fy * depth, depth);
  return T_cam_world.inverse() * Xc;
}

// Drops recent points that tracking rarely finds where predicted, or that too few keyframes
// observe two keyframes after they were made; points older than three keyframes leave probation.
void CullRecentPoints(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle current) {
  const uint64_t current_id = map.keyframe(current).id;
  const size_t min_observations = context.monocular() ? 2 : 3;
  std::vector<PointHandle> keep;
  for (PointHandle p : state.recent_points) {
    MapPoint* point = map.points().try_get(p);
    if (!point) continue;
    const uint64_t age = current_id - std::min(current_id, point->first_keyframe_id);
    if (point->found_ratio() < context.options.recent_point_min_found_ratio ||
        (age >= 2 && point->observations.size() < min_observations)) {
      map.ErasePoint(p);
    } else if (age < 3) {
      keep.push_back(p);
    }
  }
  state.recent_points = std::move(keep);
}

// Depths (metres) where new points of a keyframe may lie, from the points it already sees.
std::pair<double, double> SceneDepthRange(const Map& map, KeyFrameHandle h, double factor) {
  const KeyFrame& kf = map.keyframe(h);
  std::vector<double> depths;
  for (PointHandle p : kf.points)
    if (const MapPoint* point = map.points().try_get(p)) depths.push_back((kf.T_cam_world * point->position).z());
  if (depths.size() < 10) return {0.05, 1e4};
  std::sort(depths.begin(), depths.end());
  // Beyond the depths seen so far, both ways (SlamOptions::new_point_depth_factor).
  const double near = depths[depths.size() / 20], far = depths[depths.size() - 1 - depths.size() / 20];
  return {std::max(0.01, near / factor), factor * far};
}

void Fuse(Map& map, const SystemContext& context, KeyFrameHandle current) {
  const SlamOptions& options = context.options;
  std::vector<KeyFrameHandle> targets = map.BestCovisible(current, options.local_keyframes);
  std::unordered_set<KeyFrameHandle> in_set(targets.begin(), targets.end());
  const size_t first_order = targets.size();
  for (size_t i = 0; i < first_order; ++i)
    for (KeyFrameHandle n : map.BestCovisible(targets[i], 5))
      if (n != current && in_set.insert(n).second) targets.push_back(n);
  // The current keyframe's points into the neighbours, then the neighbours' points into it.
  std::vector<PointHandle> own;
  for (PointHandle p : map.keyframe(current).points)
    if (!p.is_null()) own.push_back(p);
  for (KeyFrameHandle t : targets) FusePoints(map, t, own, context.geometry, options.matcher);
  std::vector<PointHandle> theirs;
  std::unordered_set<PointHandle> unique;
  for (KeyFrameHandle t : targets)
    for (PointHandle p : map.keyframe(t).points)
      if (!p.is_null() && unique.insert(p).second) theirs.push_back(p);
  FusePoints(map, current, theirs, context.geometry, options.matcher);
  for (PointHandle p : map.keyframe(current).points)
    if (map.points().contains(p)) map.UpdatePointStats(p, context.map_scales);
}


// Cells per image axis of the grid over which a thin keyframe looks for the parts it does not cover.
constexpr int kThinKeyFrameGrid = 8;

// A monocular keyframe whose points (those it tracks and its new ones over min_parallax_deg) are
// fewer than thin_keyframe_points (twice the count under which tracking counts as fading) also
// takes the candidates between thin_keyframe_parallax_deg and that floor in the parts of its image
// where it holds no point, widest rays first, one per keypoint, until it holds that many. A fast
// turn into an unmapped view leaves the side it turns to empty, and the narrow rays are all a
// keyframe can place there before the view is gone; where points already lie, the floor alone
// decides, so a keyframe with its points spread over the view takes few narrow ones. The parts
// are the cells of a kThinKeyFrameGrid x kThinKeyFrameGrid grid over the image: 200 points make 3
// a cell on average, so an empty cell is a part of the view the map does not cover, not a gap
// between points. Deterministic: the candidates come in the neighbours' order, the sort is stable.
void AddNarrowPointsToAThinKeyFrame(const KeyFrame& a, const SystemContext& context,
                                    const std::vector<std::vector<std::pair<NewPoint, double>>>& narrow,
                                    std::vector<NewPoint>* out) {
  const size_t target = static_cast<size_t>(std::max(0, context.options.thin_keyframe_points));
  std::vector<uint8_t> held(a.size(), 0);
  size_t holds = 0;
  auto hold = [&](uint32_t i) {
    if (held[i]) return false;
    held[i] = 1;
    ++holds;
    return true;
  };
  for (uint32_t i = 0; i < a.size(); ++i)
    if (!a.points[i].is_null()) hold(i);
  for (const NewPoint& c : *out) hold(c.i1);
  if (holds >= target) return;
  std::vector<std::pair<NewPoint, double>> all;
  for (const std::vector<std::pair<NewPoint, double>>& n : narrow) all.insert(all.end(), n.begin(), n.end());
  std::stable_sort(all.begin(), all.end(), [](const auto& x, const auto& y) { return x.second > y.second; });
  const PinholeCamera& camera = context.geometry.camera;
  auto cell = [&](uint32_t i) {
    const int x = static_cast<int>(a.uv[i].x() * kThinKeyFrameGrid / camera.width);
    const int y = static_cast<int>(a.uv[i].y() * kThinKeyFrameGrid / camera.height);
    return std::clamp(y, 0, kThinKeyFrameGrid - 1) * kThinKeyFrameGrid + std::clamp(x, 0, kThinKeyFrameGrid - 1);
  };
  std::array<uint8_t, kThinKeyFrameGrid * kThinKeyFrameGrid> covered{};
  for (uint32_t i = 0; i < a.size(); ++i)
    if (held[i]) covered[cell(i)] = 1;
  for (const auto& [c, parallax_deg] : all) {
    if (holds >= target) break;
    if (!covered[cell(c.i1)] && hold(c.i1)) out->push_back(c);
  }
}

}  // namespace

bool FollowToLiveKeyFrame(const Map& map, const CulledKeyFrames& culled, KeyFrameHandle* ref,
                          Eigen::Isometry3d* T_cam_ref) {
  for (int hops = 0; hops < 1000 && !ref->is_null(); ++hops) {
    if (map.keyframes().contains(*ref)) return true;
    const auto it = culled.find(*ref);
    if (it == culled.end()) return false;
    *T_cam_ref = *T_cam_ref * it->second.T_kf_parent;
    *ref = it->second.parent;
  }
  return false;
}

Eigen::Isometry3d ResolveFramePose(const Map& map, const CulledKeyFrames& culled, const AnchoredFramePose& f,
                                   const Similarity3& since) {
  Eigen::Isometry3d T_cam_ref = f.T_cam_ref.isometry();
  T_cam_ref.translation() *= since.s;
  KeyFrameHandle ref = f.reference;
  if (FollowToLiveKeyFrame(map, culled, &ref, &T_cam_ref)) return T_cam_ref * map.keyframe(ref).T_cam_world;
  return MovedCameraPose(f.T_cam_world.isometry(), since);
}

void ApplySightings(Map& map, std::span<const PointHandle> visible, std::span<const PointHandle> found) {
  for (PointHandle p : visible)
    if (MapPoint* point = map.points().try_get(p)) ++point->visible;
  for (PointHandle p : found)
    if (MapPoint* point = map.points().try_get(p)) ++point->found;
}

KeyFrameHandle InsertKeyFrame(Map& map, LocalMappingState& state, const SystemContext& context, TrackedFrame& frame,
                              bool all_depth_points) {
  KeyFrame kf;
  kf.frame_index = frame.index;
  kf.t_ns = frame.t_ns;
  kf.agent = context.options.agent;
  kf.T_cam_world = frame.T_cam_world;
  kf.uv = frame.keypoints.uv;
  kf.right_u = frame.keypoints.right_u;
  kf.depth = frame.keypoints.depth;
  kf.angle = frame.keypoints.angle;
  kf.octave = frame.keypoints.octave;
  kf.descriptor = frame.keypoints.descriptor;
  kf.points.assign(frame.size(), PointHandle::null());
  const KeyFrameHandle h = map.AddKeyFrame(std::move(kf));
  for (uint32_t i = 0; i < frame.size(); ++i) {
    const PointHandle p = frame.points[i];
    if (p.is_null() || !map.points().contains(p)) continue;
    const auto& obs = map.point(p).observations;
    if (std::any_of(obs.begin(), obs.end(), [&](const Observation& o) { return o.keyframe == h; })) continue;
    map.AddObservation(p, h, i);
  }
  // New points from stereo/RGB-D depth: all close ones, and at least the nearest
  // kNearestCloseKeypoints.
  std::vector<uint32_t> by_depth;
  for (uint32_t i = 0; i < frame.size(); ++i)
    if (frame.keypoints.depth[i] > 0) by_depth.push_back(i);
  std::sort(by_depth.begin(), by_depth.end(),
            [&](uint32_t a, uint32_t b) { return frame.keypoints.depth[a] < frame.keypoints.depth[b]; });
  const double close = all_depth_points ? 1e30 : context.CloseDepth();
  int considered = 0;
  for (uint32_t i : by_depth) {
    if (frame.keypoints.depth[i] > close && considered > static_cast<int>(kNearestCloseKeypoints)) break;
    ++considered;
    if (!frame.points[i].is_null()) continue;
    const PointHandle p = map.AddPoint(
        Unproject(context.geometry.camera, frame.T_cam_world, frame.keypoints.uv[i], frame.keypoints.depth[i]), h);
    map.AddObservation(p, h, i);
    map.UpdatePointStats(p, context.map_scales);
    frame.points[i] = p;
    state.recent_points.push_back(p);
  }
  map.UpdateCovisibility(h);
  return h;
}

InsertedTwoView InsertTwoViewMap(Map& map, LocalMappingState& state, const SystemContext& context, TwoViewMap& two_view,
                                 TrackedFrame& second) {
  // Points from the two views only: a monocular camera measures no depth.
  InsertedTwoView out;
  out.first = InsertKeyFrame(map, state, context, two_view.first);
  out.second = InsertKeyFrame(map, state, context, second);
  for (size_t k = 0; k < two_view.pairs.size(); ++k) {
    if (!two_view.triangulated[k]) continue;
    const PointHandle p = map.AddPoint(two_view.X_world[k], out.first);
    map.AddObservation(p, out.first, two_view.pairs[k].first);
    map.AddObservation(p, out.second, two_view.pairs[k].second);
    map.UpdatePointStats(p, context.map_scales);
    second.points[two_view.pairs[k].second] = p;
    ++out.points;
  }
  map.UpdateCovisibility(out.first);
  map.UpdateCovisibility(out.second);
  return out;
}

bool PrepareKeyFrame(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle keyframe,
                     std::pair<double, double>* depth_range) {
  if (!map.keyframes().contains(keyframe)) return false;
  for (PointHandle p : map.keyframe(keyframe).points)
    if (map.points().contains(p)) map.UpdatePointStats(p, context.map_scales);
  map.UpdateCovisibility(keyframe);
  CullRecentPoints(map, state, context, keyframe);
  *depth_range = SceneDepthRange(map, keyframe, context.options.new_point_depth_factor);
  // Copies of the keyframes to triangulate against, so matching runs without map access;
  // assigned over the last keyframe's copies, whose buffers they reuse.
  state.neighbours = map.BestCovisible(keyframe, context.options.local_keyframes);
  state.snapshot.resize(state.neighbours.size() + 1);
  state.snapshot[0] = map.keyframe(keyframe);
  for (size_t k = 0; k < state.neighbours.size(); ++k) state.snapshot[k + 1] = map.keyframe(state.neighbours[k]);
  return true;
}

std::vector<NewPoint> FindNewPoints(const LocalMappingState& state, const SystemContext& context,
                                    std::pair<double, double> depth_range) {
  const CameraGeometry& geometry = context.geometry;
  const std::vector<KeyFrame>& snapshot = state.snapshot;
  const double baseline = geometry.bf / geometry.camera.fx;
  TriangulationOptions tri;
  tri.max_reprojection_error_px = 2.0;
  tri.min_parallax_deg = 0.0;
  const double max_ray_cos = std::cos(context.options.min_parallax_deg * M_PI / 180.0);
  const double thin_parallax_deg = context.options.thin_keyframe_parallax_deg;
  const bool thin_floor = thin_parallax_deg > 0 && thin_parallax_deg < context.options.min_parallax_deg;
  const KeyFrame& a = snapshot[0];
  // Each neighbour is matched on its own (a task per neighbour, the keyframes are copies); the
  // candidates are joined in the neighbours' order, as one loop over them would list them.
  std::vector<std::vector<NewPoint>> found(state.neighbours.size());
  std::vector<std::vector<std::pair<NewPoint, double>>> narrow(state.neighbours.size());  // with their parallax
  tbb::parallel_for(size_t{0}, state.neighbours.size(), [&](size_t k) {
    std::vector<NewPoint>& out = found[k];
    const KeyFrame& b = snapshot[k + 1];
    // Monocular pairs need parallax, which the triangulation test below checks per point.
    if ((a.camera_center() - b.camera_center()).norm() < baseline) return;
    const Eigen::Matrix3d F = FundamentalBetween(a, b, geometry.camera);
    for (const auto& [i1, i2] : MatchForTriangulation(a, b, F, depth_range, geometry, context.options.matcher)) {
      const TriangulatedPoint t = TriangulatePoint(geometry.camera, a.T_cam_world, b.T_cam_world,
                                                   a.uv[i1].cast<double>(), b.uv[i2].cast<double>(), tri);
      Eigen::Vector3d X;
      // Rays that diverge by min_parallax_deg are triangulated; otherwise the stereo or RGB-D
      // depth of the keyframe that sees the point nearer (the wider stereo angle) places it, at
      // any depth: far points, whose rays barely diverge between keyframes on fast forward
      // motion, enter the map from their disparity.
      const double ray_cos = std::cos(t.parallax_deg * M_PI / 180.0);
      const bool depth_a = a.depth[i1] > 0, depth_b = b.depth[i2] > 0;
      bool is_narrow = false;
      if (t.ok() && ray_cos < max_ray_cos) {
        X = t.X_world;
      } else if (thin_floor && t.ok() && !depth_a && !depth_b && t.parallax_deg >= thin_parallax_deg) {
        X = t.X_world;  // kept aside: taken only if the keyframe holds too few points without it
        is_narrow = true;
      } else if (depth_a && (!depth_b || a.depth[i1] <= b.depth[i2])) {
        X = Unproject(geometry.camera, a.T_cam_world, a.uv[i1], a.depth[i1]);
      } else if (depth_b) {
        X = Unproject(geometry.camera, b.T_cam_world, b.uv[i2], b.depth[i2]);
      } else {
        continue;
      }
      // Every measurement must agree: both projections, and the right image where there is one.
      auto agrees = [&](const KeyFrame& kf, uint32_t i) {
        const Eigen::Vector3d Xc = kf.T_cam_world * X;
        if (Xc.z() <= 0) return false;
        const double u = geometry.camera.fx * Xc.x() / Xc.z() + geometry.camera.cx;
        const double v = geometry.camera.fy * Xc.y() / Xc.z() + geometry.camera.cy;
        const double eu = u - kf.uv[i].x(), ev = v - kf.uv[i].y();
        double e2 = eu * eu + ev * ev, gate = 5.991;
        if (kf.right_u[i] >= 0) {
          const double er = u - geometry.bf / Xc.z() - kf.right_u[i];
          e2 += er * er;
          gate = 7.8;
        }
        return e2 * geometry.pyramid.inv_sigma2[kf.octave[i]] < gate;
      };
      if (!agrees(a, i1) || !agrees(b, i2)) continue;
      if (is_narrow)
        narrow[k].push_back({{state.neighbours[k], i1, i2, X}, t.parallax_deg});
      else
        out.push_back({state.neighbours[k], i1, i2, X});
    }
  });
  std::vector<NewPoint> out;
  for (const std::vector<NewPoint>& f : found) out.insert(out.end(), f.begin(), f.end());
  if (thin_floor) AddNarrowPointsToAThinKeyFrame(a, context, narrow, &out);
  return out;
}

void AddNewPointsAndFuse(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle current,
                         std::span<const NewPoint> candidates, bool add_points) {
  if (add_points) {
    for (const NewPoint& c : candidates) {
      // The map moved on while matching ran: skip anything erased or bound since.
      const KeyFrame* b = map.keyframes().try_get(c.neighbour);
      if (!b || !b->points[c.i2].is_null() || !map.keyframe(current).points[c.i1].is_null()) continue;
      const PointHandle p = map.AddPoint(c.X_world, current);
      map.AddObservation(p, current, c.i1);
      map.AddObservation(p, c.neighbour, c.i2);
      map.UpdatePointStats(p, context.map_scales);
      state.recent_points.push_back(p);
    }
  }
  Fuse(map, context, current);
  map.UpdateCovisibility(current);
}

bool BuildLocalBundleAdjustment(const Map& map, LocalMappingState& state, const SystemContext& context,
                                KeyFrameHandle current, KeyFrameHandle anchor) {
  if (!map.keyframes().contains(current)) return false;
  // The window: the new keyframe and its strongest covisible ones; every other keyframe that
  // sees their points enters fixed.
  thread_local std::vector<KeyFrameHandle> window;
  window.assign(1, current);
  for (const auto& [n, w] : map.keyframe(current).covisible) {
    if (window.size() > context.options.max_local_ba_keyframes) break;  // covisible: strongest first
    if (map.keyframes().contains(n)) window.push_back(n);
  }
  BuildMapBundleAdjustment(map, context.geometry, context.stereo_depth, window, anchor, 1, &state.local_ba);
  return !state.local_ba.problem.observations.empty();
}

BundleAdjustmentResult SolveLocalBundleAdjustment(LocalMappingState& state, const SystemContext& context,
                                                  std::function<bool()> stop_early) {
  BundleAdjustmentOptions options = context.options.bundle_adjustment;
  options.stop_early = std::move(stop_early);
  const BundleAdjustmentResult result =
      LocalBundleAdjustment(state.local_ba.problem, options, &state.local_ba_workspace);
  if (result.stopped_early) ++state.times.local_ba_stopped_early;
  return result;
}

void ApplyLocalBundleAdjustment(Map& map, const LocalMappingState& state, const SystemContext& context,
                                const BundleAdjustmentResult& result) {
  ApplyMapBundleAdjustment(state.local_ba, result, /*erase_outliers=*/true, &map);
  for (PointHandle p : state.local_ba.points)
    if (map.points().contains(p)) map.UpdatePointStats(p, context.map_scales);
}

void CullKeyFrames(Map& map, LocalMappingState& state, const SystemContext& context, KeyFrameHandle current,
                   std::span<const KeyFrameHandle> keep,
                   const std::function<void(KeyFrameHandle, const KeyFrame&)>& before_erase) {
  if (!map.keyframes().contains(current)) return;
  const bool monocular = context.monocular();
  for (const auto& [h, w] : std::vector<std::pair<KeyFrameHandle, int>>(map.keyframe(current).covisible)) {
    if (std::find(keep.begin(), keep.end(), h) != keep.end() || !map.keyframes().contains(h)) continue;
    const KeyFrame& kf = map.keyframe(h);
    if (!kf.loop_edges.empty()) continue;  // loop closures keep both ends
    int considered = 0, redundant = 0;
    const double close = context.CloseDepth();
    for (uint32_t i = 0; i < kf.size(); ++i) {
      const MapPoint* point = map.points().try_get(kf.points[i]);
      if (!point) continue;
      // With depth, only reliable close points count.
      if (!monocular && (kf.depth[i] <= 0 || kf.depth[i] > close)) continue;
      ++considered;
      if (point->observations.size() <= 3) continue;
      int others = 0;
      for (const Observation& o : point->observations) {
        if (o.keyframe == h) continue;
        const KeyFrame* other = map.keyframes().try_get(o.keyframe);
        if (other && other->octave[o.keypoint] <= kf.octave[i] + 1) ++others;
        if (others >= 3) break;
      }
      if (others >= 3) ++redundant;
    }
    if (considered > 0 && redundant > context.options.redundant_keyframe_ratio * considered) {
      if (before_erase) before_erase(h, kf);
      // Frames that referred to the culled keyframe follow its parent from now on.
      if (const KeyFrame* parent = map.keyframes().try_get(kf.parent))
        state.culled[h] = {kf.parent, kf.T_cam_world * parent->T_cam_world.inverse()};
      map.EraseKeyFrame(h);
    }
  }
}

}  // namespace flatslam
