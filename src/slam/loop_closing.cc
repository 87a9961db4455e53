// Slam's place recognition: bag-of-words for frames and keyframes, relocalization against the
// keyframe database, loop detection with temporal consistency and geometric verification, loop
// correction through the essential graph, and global bundle adjustment in the background.
#include <algorithm>
#include <cstdio>
#include <chrono>
#include <unordered_map>
#include <unordered_set>

#include <opencv2/calib3d.hpp>

#include "core/error.h"
#include "mapping/essential_graph.h"
#include "place/place_verification.h"
#include "geometry/similarity.h"
#include "slam/slam.h"
#include "place/vocabulary.h"

namespace flatslam {

// A verified loop: the corrected pose of the current keyframe (S_cw), its loop-side point per
// keypoint (matched) and the points of the candidate and its neighbours (nearby).
struct Slam::LoopMatch : PlaceMatch {
  KeyFrameHandle candidate;
};

namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

}  // namespace

void Slam::ComputeBow(TrackedFrame& frame) const {
  if (!options_.vocabulary || !frame.bow.empty()) return;
  options_.vocabulary->Transform(frame.keypoints.descriptor, &frame.bow, &frame.bow_features);
}

void Slam::ForceLost() {
  std::lock_guard<std::mutex> lock(map_mutex_);
  force_lost_ = true;
}

void Slam::AdoptMap(Map&& map, std::span<const AnchoredFramePose> frames) {
  FLATSLAM_CHECK(options_.vocabulary, "continuing a saved map needs a vocabulary to relocalize in it");
  std::lock_guard<std::mutex> lock(map_mutex_);
  FLATSLAM_CHECK(state_ == TrackingState::kNotInitialized && map_.keyframes().empty(),
                 "a map can only be adopted before the first frame");
  FLATSLAM_CHECK(!map.keyframes().empty(), "the map to continue has no keyframes");
  map_ = std::move(map);
  const auto handles = map_.keyframes().handles();
  const std::vector<KeyFrameHandle> kfs(handles.begin(), handles.end());
  for (KeyFrameHandle h : kfs) {
    KeyFrame& kf = map_.keyframe(h);
    options_.vocabulary->Transform(kf.descriptor, &kf.bow, &kf.bow_features);
    database_.Add(h, kf.bow);
    // A spanning-tree root anchors the map's frame (bundle adjustment holds it fixed).
    if (first_keyframe_.is_null() || (kf.parent.is_null() && !map_.keyframe(first_keyframe_).parent.is_null()))
      first_keyframe_ = h;
  }
  for (FramePose pose : frames) {
    if (!map_.keyframes().contains(pose.reference)) pose.reference = KeyFrameHandle::null();
    frame_poses_.push_back(pose);
  }
  // Points the continued session still had on probation (made by its last three keyframes) stay
  // on probation here, so that recent-point culling drops the bad ones as it would have.
  uint64_t newest = 0;
  for (const KeyFrame& kf : map_.keyframes().values()) {
    newest = std::max(newest, kf.id);
    last_keyframe_frame_ = std::max(last_keyframe_frame_, kf.frame_index);
  }
  for (PointHandle p : map_.points().handles())
    if (map_.point(p).first_keyframe_id + 3 > newest) recent_points_.push_back(p);
  segment_keyframes_ = map_.keyframes().size();
  state_ = TrackingState::kLost;
  allow_new_segments_ = false;
}

void Slam::CaptureState(State* out) const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  out->map.AssignForSnapshot(map_);
  frame_poses_.TakeView(&out->frames);
  out->culled = culled_;
  out->next_frame = next_frame_;
}

void Slam::State::AnchoredToMap(std::vector<AnchoredFramePose>* out) const {
  out->resize(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    AnchoredFramePose a = frames[i];
    Eigen::Isometry3d T_cam_ref = a.T_cam_ref.isometry();
    if (FollowToLiveKeyFrame(map, culled, &a.reference, &T_cam_ref))
      a.T_cam_ref = CompactPose(T_cam_ref);
    else
      a.reference = KeyFrameHandle::null();
    (*out)[i] = a;
  }
}

void Slam::Warn(const std::string& message) const {
  if (warning_sink_)
    warning_sink_(message);
  else
    std::fprintf(stderr, "warning: %s\n", message.c_str());
}

void Slam::EraseKeyFrame(KeyFrameHandle kf) {
  const KeyFrame* k = map_.keyframes().try_get(kf);
  if (!k) return;
  database_.Erase(kf, k->bow);
  // Frames that referred to kf follow its parent from now on (see ResolveFramePose).
  if (const KeyFrame* parent = map_.keyframes().try_get(k->parent))
    culled_[kf] = {k->parent, k->T_cam_world * parent->T_cam_world.inverse()};
  map_.EraseKeyFrame(kf);
}

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

Eigen::Isometry3d Slam::ResolveFramePose(const FramePose& f) const {
  Eigen::Isometry3d T_cam_ref = f.T_cam_ref.isometry();
  KeyFrameHandle ref = f.reference;
  if (FollowToLiveKeyFrame(map_, culled_, &ref, &T_cam_ref)) return T_cam_ref * map_.keyframe(ref).T_cam_world;
  return f.T_cam_world.isometry();  // no live keyframe to follow: the pose as tracked
}

bool Slam::Relocalize(TrackedFrame& frame) {
  if (!options_.vocabulary || database_.size() == 0) return false;
  ComputeBow(frame);
  std::vector<PlaceCandidate> candidates = database_.DetectRelocalizationCandidates(map_, frame.bow);
  if (candidates.size() > 20) candidates.resize(20);
  const PinholeCamera& cam = geometry_.camera;
  const cv::Matx33d K(cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
  for (const PlaceCandidate& c : candidates) {
    const KeyFrame* kf = map_.keyframes().try_get(c.keyframe);
    if (!kf) continue;
    std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
    if (MatchByBow(frame, *kf, map_, options_.matcher, 0.75f) < 15) continue;
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> image;
    std::vector<uint32_t> index;
    for (uint32_t i = 0; i < frame.size(); ++i) {
      const MapPoint* point = map_.points().try_get(frame.points[i]);
      if (!point) continue;
      object.emplace_back(point->position.x(), point->position.y(), point->position.z());
      image.emplace_back(frame.keypoints.uv[i].x(), frame.keypoints.uv[i].y());
      index.push_back(i);
    }
    cv::Mat rvec, tvec;
    std::vector<int> inliers;
    const bool solved = cv::solvePnPRansac(object, image, K, cv::noArray(), rvec, tvec, false, 200, 6.0f, 0.99, inliers,
                                           cv::SOLVEPNP_EPNP);
    if (!solved || inliers.size() < 10) continue;
    std::vector<char> keep(index.size(), 0);
    for (int k : inliers) keep[k] = 1;
    for (size_t k = 0; k < index.size(); ++k)
      if (!keep[k]) frame.points[index[k]] = PointHandle::null();
    cv::Mat R;
    cv::Rodrigues(rvec, R);
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    for (int r = 0; r < 3; ++r) {
      for (int col = 0; col < 3; ++col) T.linear()(r, col) = R.at<double>(r, col);
      T.translation()(r) = tvec.at<double>(r);
    }
    frame.T_cam_world = T;
    int good = OptimizeFramePose(frame);
    if (good < 10) continue;
    if (good < 50) {
      MatchByProjection(frame, *kf, map_, geometry_, 10.0f, options_.matcher);
      good = OptimizeFramePose(frame);
    }
    if (good < 50) continue;
    reference_keyframe_ = c.keyframe;
    return true;
  }
  std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
  return false;
}

void Slam::DetectAndCloseLoop(KeyFrameHandle current) {
  if (!options_.vocabulary) return;
  std::lock_guard<std::mutex> lock(map_mutex_);
  const KeyFrame* kf = map_.keyframes().try_get(current);
  if (!kf || kf->bow.empty()) return;
  const bool detect = options_.loop_closing && !global_ba_running_ && map_.keyframes().size() > 10 &&
                      (loop_closures_.empty() || keyframes_since_loop_ >= 10);
  ++keyframes_since_loop_;
  std::vector<PlaceCandidate> candidates;
  if (detect) {
    // The loop must score at least as well as the least similar covisible keyframe.
    float min_score = 1;
    for (const auto& [n, w] : kf->covisible)
      if (const KeyFrame* other = map_.keyframes().try_get(n))
        min_score = std::min(min_score, Vocabulary::Score(kf->bow, other->bow));
    if (kf->covisible.empty()) min_score = 0;
    candidates = database_.DetectLoopCandidates(map_, current, min_score);
  }
  database_.Add(current, kf->bow);
  if (!detect) return;

  // Temporal consistency: a candidate's covisibility group must overlap groups that earlier
  // keyframes also found, loop_consistency times in a row.
  std::vector<ConsistentGroup> next;
  std::vector<KeyFrameHandle> consistent;
  std::vector<bool> extended(consistent_groups_.size(), false);
  for (const PlaceCandidate& c : candidates) {
    ConsistentGroup group;
    group.keyframes.push_back(c.keyframe);
    for (const auto& [n, w] : map_.keyframe(c.keyframe).covisible) group.keyframes.push_back(n);
    std::sort(group.keyframes.begin(), group.keyframes.end());
    bool found = false, enough = false;
    for (size_t g = 0; g < consistent_groups_.size(); ++g) {
      const auto& previous = consistent_groups_[g].keyframes;
      const bool overlap = std::any_of(group.keyframes.begin(), group.keyframes.end(), [&](KeyFrameHandle h) {
        return std::binary_search(previous.begin(), previous.end(), h);
      });
      if (!overlap) continue;
      found = true;
      const int count = consistent_groups_[g].count + 1;
      if (!extended[g]) {
        next.push_back({group.keyframes, count});
        extended[g] = true;
      }
      if (count >= options_.loop_consistency) enough = true;
    }
    if (enough) consistent.push_back(c.keyframe);
    if (!found) next.push_back({group.keyframes, 0});
  }
  consistent_groups_ = std::move(next);
  for (KeyFrameHandle candidate : consistent) {
    LoopMatch match;
    if (!VerifyLoop(current, candidate, &match)) continue;
    if (options_.inject_fault == InjectedFault::kLoopClosing) Fail("injected failure in loop correction");
    CorrectLoop(current, match);
    consistent_groups_.clear();
    keyframes_since_loop_ = 0;
    if (options_.global_bundle_adjustment && !abandon_background_) {
      global_ba_running_ = true;
      // A failure here costs the refinement, not the session: it becomes a warning.
      auto task = [this, loops = loop_closures_.size()] {
        try {
          GlobalBundleAdjustment(loops);
        } catch (const std::exception& e) {
          global_ba_running_ = false;
          Warn(std::string("global bundle adjustment failed, the map keeps its loop correction: ") + e.what());
        }
      };
      if (background_)
        background_(std::move(task));
      else
        task();
    }
    return;
  }
}

bool Slam::VerifyLoop(KeyFrameHandle current, KeyFrameHandle candidate, LoopMatch* out) {
  PlaceVerificationOptions verification;
  verification.ransac.fix_scale = !monocular();
  std::optional<PlaceMatch> match =
      VerifyPlace(map_.keyframe(current), map_, candidate, map_, geometry_, options_.matcher, verification, loop_rng_);
  if (!match) return false;
  static_cast<PlaceMatch&>(*out) = std::move(*match);
  out->candidate = candidate;
  return out->matches >= options_.min_loop_matches;
}

void Slam::CorrectLoop(KeyFrameHandle current, const LoopMatch& m) {
  const auto start = std::chrono::steady_clock::now();
  const Eigen::Vector3d old_center = map_.keyframe(current).camera_center();
  map_.UpdateCovisibility(current);

  // 1. The current keyframe and its neighbours move rigidly with the loop correction.
  std::vector<KeyFrameHandle> connected = {current};
  for (const auto& [n, w] : map_.keyframe(current).covisible) connected.push_back(n);
  std::unordered_map<KeyFrameHandle, Similarity3> corrected, uncorrected;
  const Eigen::Isometry3d T_world_current = map_.keyframe(current).T_cam_world.inverse();
  for (KeyFrameHandle k : connected) {
    const Eigen::Isometry3d T_kw = map_.keyframe(k).T_cam_world;
    uncorrected[k] = Similarity3::FromIsometry(T_kw);
    corrected[k] = k == current ? m.S_cw : Similarity3::FromIsometry(T_kw * T_world_current) * m.S_cw;
  }
  std::unordered_map<PointHandle, KeyFrameHandle> corrected_by;
  for (KeyFrameHandle k : connected) {
    for (PointHandle p : map_.keyframe(k).points) {
      if (!map_.points().contains(p) || corrected_by.count(p)) continue;
      corrected_by[p] = k;
      MapPoint& point = map_.point(p);
      point.position = corrected[k].inverse() * (uncorrected[k] * point.position);
    }
  }
  for (KeyFrameHandle k : connected) map_.keyframe(k).T_cam_world = corrected[k].ToIsometry();

  // 2. Fuse the loop: the current keyframe takes the loop-side points, its neighbours too.
  map_.BindMatchedPoints(current, m.matched);
  for (KeyFrameHandle k : connected)
    if (map_.keyframes().contains(k)) FusePoints(map_, k, m.nearby, geometry_, options_.matcher);

  // 3. New covisibility links across the loop.
  std::unordered_set<KeyFrameHandle> connected_set(connected.begin(), connected.end());
  std::vector<std::pair<KeyFrameHandle, KeyFrameHandle>> loop_links;
  for (KeyFrameHandle k : connected) {
    if (!map_.keyframes().contains(k)) continue;
    std::unordered_set<KeyFrameHandle> before;
    for (const auto& [n, w] : map_.keyframe(k).covisible) before.insert(n);
    map_.UpdateCovisibility(k);
    for (const auto& [n, w] : map_.keyframe(k).covisible)
      if (!before.count(n) && !connected_set.count(n)) loop_links.emplace_back(k, n);
  }

  // 4. Essential graph: spanning tree, loop edges, strong covisibility, the new loop links. The
  // connected keyframes already sit at their corrected poses; their edges are measured from the
  // poses before the correction.
  EssentialGraph graph = EssentialGraph::OfMap(map_);
  std::vector<Similarity3> measured = graph.S;
  for (uint32_t i = 0; i < graph.nodes.size(); ++i) {
    if (const auto it = uncorrected.find(graph.nodes[i]); it != uncorrected.end()) measured[i] = it->second;
    graph.fixed[i] = graph.nodes[i] == m.candidate;
  }
  for (const auto& [k, n] : loop_links) {
    const uint32_t i = graph.index.at(k), j = graph.index.at(n);
    const auto& cov = map_.keyframe(k).covisible;
    const auto w = std::find_if(cov.begin(), cov.end(), [&](const auto& l) { return l.first == n; });
    if (k != current && n != m.candidate && (w == cov.end() || w->second < 100)) continue;
    graph.edges.Add(i, j, graph.S[i] * graph.S[j].inverse());
  }
  graph.AddMapEdges(map_, measured, 100, [](uint32_t, uint32_t) { return true; });
  {
    const uint32_t i = graph.index.at(current), j = graph.index.at(m.candidate);
    graph.edges.Add(i, j, graph.S[i] * graph.S[j].inverse());
  }
  PoseGraphOptions graph_options;
  graph_options.fix_scale = !monocular();
  OptimizePoseGraph(graph.S, graph.fixed, graph.edges.edges(), graph_options);

  // 5. Write back: keyframes take the optimized poses; points follow the keyframe that moved them.
  graph.Apply(&map_, [&](PointHandle p, const MapPoint& point) {
    const auto by = corrected_by.find(p);
    return by != corrected_by.end() ? by->second : point.reference;
  });
  for (PointHandle p : map_.points().handles()) map_.UpdatePointStats(p, map_scales_);
  map_.AddLoopEdge(current, m.candidate);
  map_corrected_ = true;
  ++map_epoch_;

  LoopClosure closure;
  closure.frame_index = map_.keyframe(current).frame_index;
  closure.matched_frame_index = map_.keyframe(m.candidate).frame_index;
  closure.t_ns = map_.keyframe(current).t_ns;
  closure.matched_t_ns = map_.keyframe(m.candidate).t_ns;
  closure.matches = m.matches;
  closure.scale = m.S_cw.s;
  closure.correction_m = (map_.keyframe(current).camera_center() - old_center).norm();
  closure.correction_ms = MsSince(start);
  loop_closures_.push_back(closure);
}

void Slam::GlobalBundleAdjustment(size_t loops) {
  struct Clear {
    std::atomic<bool>& flag;
    ~Clear() { flag = false; }
  } clear{global_ba_running_};
  if (options_.inject_fault == InjectedFault::kGlobalBundleAdjustment)
    Fail("injected failure in global bundle adjustment");
  MapBundleAdjustment ba;
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    const auto kfs = map_.keyframes().handles();
    if (kfs.empty()) return;
    // The gauge: the map's first keyframe (never culled), else any one.
    const KeyFrameHandle anchor = map_.keyframes().contains(first_keyframe_) ? first_keyframe_ : kfs.front();
    BuildMapBundleAdjustment(map_, geometry_, stereo_depth_, kfs, anchor, 2, &ba);
  }
  if (ba.problem.observations.empty()) return;
  BundleAdjustmentOptions options = options_.bundle_adjustment;
  options.linear_solver = BundleAdjustmentOptions::LinearSolver::kSparseSchur;
  options.stop_early = [this] { return abandon_background_.load(); };
  const BundleAdjustmentResult result = flatslam::LocalBundleAdjustment(ba.problem, options);
  if (!result.success || abandon_background_) return;

  std::lock_guard<std::mutex> lock(map_mutex_);
  if (loop_closures_.size() != loops) return;  // a newer loop moved the map: this solution is stale
  // Keyframes in the solution take it; keyframes made since follow their spanning-tree parent.
  std::unordered_map<KeyFrameHandle, Eigen::Isometry3d> before, after;
  for (size_t k = 0; k < ba.keyframes.size(); ++k) {
    const KeyFrame* kf = map_.keyframes().try_get(ba.keyframes[k]);
    if (!kf) continue;
    before[ba.keyframes[k]] = kf->T_cam_world;
    after[ba.keyframes[k]] = ba.problem.poses[k].T_cam_world;
  }
  ApplyMapBundleAdjustment(ba, result, /*erase_outliers=*/false, &map_);
  bool progress = true;
  while (progress) {
    progress = false;
    for (KeyFrameHandle h : map_.keyframes().handles()) {
      if (after.count(h)) continue;
      KeyFrame& kf = map_.keyframe(h);
      const auto parent_before = before.find(kf.parent);
      if (parent_before == before.end()) continue;
      before[h] = kf.T_cam_world;
      kf.T_cam_world = kf.T_cam_world * parent_before->second.inverse() * after.at(kf.parent);
      after[h] = kf.T_cam_world;
      progress = true;
    }
  }
  const std::unordered_set<PointHandle> solved(ba.points.begin(), ba.points.end());
  for (PointHandle p : map_.points().handles()) {
    if (solved.count(p)) continue;
    MapPoint& point = map_.point(p);
    const auto b = before.find(point.reference);
    if (b == before.end()) continue;
    point.position = after.at(point.reference).inverse() * (b->second * point.position);
  }
  for (PointHandle p : map_.points().handles()) map_.UpdatePointStats(p, map_scales_);
  map_corrected_ = true;
  ++map_epoch_;
}

}  // namespace flatslam
