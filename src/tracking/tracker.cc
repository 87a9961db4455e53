#include "tracking/tracker.h"

#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

#include <opencv2/calib3d.hpp>

#include "geometry/geometry.h"
#include "matching/matcher.h"
#include "optimization/pose_optimizer.h"
#include "place/vocabulary.h"

namespace flatslam {
namespace {

// The frame's bag of words, computed once (reference tracking and relocalization both use it).
void ComputeFrameWords(const Vocabulary& vocabulary, TrackedFrame& frame) {
  if (frame.bow.empty()) vocabulary.Transform(frame.keypoints.descriptor, &frame.bow, &frame.bow_features);
}

// Keypoints of the frame matched to a map point.
int MatchedCount(const TrackedFrame& frame) {
  return static_cast<int>(
      std::count_if(frame.points.begin(), frame.points.end(), [](PointHandle p) { return !p.is_null(); }));
}

// Distance (pixels) between where the frame's matched points project from the predicted pose and
// from the tracked one: its quantile over the points (the median by default).
float PredictionError(const Map& map, const PinholeCamera& camera, const Eigen::Isometry3d& predicted,
                      const TrackedFrame& frame, double quantile = 0.5) {
  thread_local std::vector<float> errors;
  errors.clear();
  for (PointHandle p : frame.points) {
    const MapPoint* point = map.points().try_get(p);
    if (!point) continue;
    const Eigen::Vector3d a = predicted * point->position, b = frame.T_cam_world * point->position;
    if (a.z() <= 0 || b.z() <= 0) continue;
    errors.push_back(static_cast<float>((camera.Project(a) - camera.Project(b)).norm()));
  }
  if (errors.empty()) return 0;
  const size_t k = std::min(errors.size() - 1, static_cast<size_t>(quantile * static_cast<double>(errors.size())));
  std::nth_element(errors.begin(), errors.begin() + k, errors.end());
  return errors[k];
}

// The constant-velocity prediction of a frame taken at t_ns: the last step's motion continued
// for as many frame periods as have passed since the last frame (a dropped frame or a skipped
// unreadable one makes that two or more; KITTI 06 stereo with 7 frames dropped went from 0.035
// to 1.16 m when the step was replayed as it was). Times are counted in whole periods of the
// camera's frame rate, so timestamp jitter (KITTI's times.txt varies by 0.1 ms a frame while
// the cameras are triggered at a fixed rate) changes nothing; with the rate unknown the times
// are taken as they are. nullopt without a velocity.
std::optional<Eigen::Isometry3d> PredictedPose(const TrackerState& s, int64_t t_ns, double frame_rate_hz) {
  if (!s.velocity || !s.last_frame) return std::nullopt;
  const Eigen::Isometry3d step = *s.velocity;
  double now = static_cast<double>(t_ns - s.last_frame->t_ns), then = static_cast<double>(s.velocity_dt_ns);
  if (now <= 0 || then <= 0) return Eigen::Isometry3d(step * s.last_frame->T_cam_world);
  if (frame_rate_hz > 0) {
    const double period_ns = 1e9 / frame_rate_hz;
    now = std::max(1.0, std::round(now / period_ns));
    then = std::max(1.0, std::round(then / period_ns));
  }
  if (now == then) return Eigen::Isometry3d(step * s.last_frame->T_cam_world);
  return Eigen::Isometry3d(ScaledMotion(step, now / then) * s.last_frame->T_cam_world);
}

// One frame's tracking: the map, the tracker's memory and what it asks of mapping.
struct Tracking {
  const Map& map;
  const KeyFrameDatabase& database;
  const SystemContext& context;
  const SlamOptions& options;
  TrackerState& s;
  TrackResult& result;

  bool monocular() const { return context.monocular(); }

  // The search window around a predicted point: motion_search_radius, or wider where the camera's
  // recent motion was predicted worse than that (see TrackerState::prediction_error_px). Twice the
  // median error covers about nine points in ten (hand-held EuRoC at 5 Hz: the 90th percentile of
  // a frame's errors is 1.3-2x its median).
  float MotionSearchRadius() const { return std::max(options.motion_search_radius, 2.0f * s.prediction_error_px); }

  // Stereo/RGB-D: the frame starts a map segment when enough keypoints have depth.
  bool PlanInitialize(TrackedFrame& frame) {
    if (std::count_if(frame.keypoints.depth.begin(), frame.keypoints.depth.end(), [](float d) { return d > 0; }) <
        options.min_init_points)
      return false;
    if (s.first_keyframe.is_null()) frame.T_cam_world = Eigen::Isometry3d::Identity();
    std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
    s.segment_keyframes = 0;
    result.insert = TrackResult::Insert::kFirstKeyFrame;
    return true;
  }

  bool PlanMonocularInitialize(TrackedFrame& frame) {
    if (!s.init_frame || static_cast<int>(frame.size()) <= options.min_init_matches) {
      if (static_cast<int>(frame.size()) > options.min_init_matches) s.init_frame = frame;
      return false;
    }
    const auto pairs = MatchForInitialization(*s.init_frame, frame, options.init_search_px, options.matcher);
    if (static_cast<int>(pairs.size()) < options.min_init_matches) {
      s.init_frame = frame;  // too little overlap left: start again from this frame
      return false;
    }
    std::vector<Eigen::Vector2d> px1, px2;
    for (const auto& [i1, i2] : pairs) {
      px1.push_back(s.init_frame->keypoints.uv[i1].cast<double>());
      px2.push_back(frame.keypoints.uv[i2].cast<double>());
    }
    const std::optional<TwoViewResult> two_view =
        InitializeTwoView(px1, px2, context.geometry.camera, TwoViewOptions{}, s.rng);
    if (!two_view) return false;

    // Two keyframes: the first frame at the origin (or the last pose of a previous segment), the
    // current one at the recovered motion; points are in first-frame coordinates.
    const Eigen::Isometry3d T_first_world =
        s.first_keyframe.is_null() ? Eigen::Isometry3d::Identity() : s.init_frame->T_cam_world;
    TwoViewMap& plan = result.two_view.emplace();
    plan.first = std::move(*s.init_frame);
    plan.first.T_cam_world = T_first_world;
    std::fill(plan.first.points.begin(), plan.first.points.end(), PointHandle::null());
    std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
    frame.T_cam_world = two_view->T_2_1 * T_first_world;
    s.segment_keyframes = 0;
    const Eigen::Isometry3d T_world_first = T_first_world.inverse();
    int created = 0;
    plan.pairs = pairs;
    plan.X_world.resize(pairs.size());
    plan.triangulated.assign(pairs.size(), 0);
    for (size_t k = 0; k < pairs.size(); ++k) {
      if (!two_view->triangulated[k]) continue;
      plan.X_world[k] = T_world_first * two_view->points[k];
      plan.triangulated[k] = 1;
      ++created;
    }
    result.insert = TrackResult::Insert::kTwoView;
    s.velocity.reset();
    s.init_frame.reset();
    return created >= options.min_init_matches / 2;
  }

  bool TrackWithMotion(TrackedFrame& frame, const std::optional<Eigen::Isometry3d>& predicted) {
    if (!predicted) return false;
    frame.T_cam_world = *predicted;
    std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
    const float radius = MotionSearchRadius();
    int matches = MatchByProjection(frame, *s.last_frame, map, context.geometry, radius, options.matcher);
    if (matches < options.min_motion_matches) {
      std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
      matches = MatchByProjection(frame, *s.last_frame, map, context.geometry, 2 * radius, options.matcher);
    }
    if (matches < options.min_motion_matches) return false;
    // A pose carried by a sliver of the last frame's matches is more likely wrong than right:
    // the reference keyframe search (wider, without the motion prior) gets a say.
    const int inliers = OptimizeFramePose(map, context, frame);
    return inliers >= options.min_motion_inliers && inliers * 8 >= s.last_inliers;
  }

  bool TrackReferenceKeyFrame(TrackedFrame& frame) {
    if (!s.last_frame) return false;
    const KeyFrame* reference = map.keyframes().try_get(s.reference_keyframe);
    if (!reference) return false;
    // Without a motion prior, two searches from the last pose; the pose with more inliers wins.
    // Around the last pose, wide: finds what moved less than the window, which under fast motion
    // is mostly far points, whose pose then has almost no translation (KITTI 06 at 2.4 m a frame:
    // 0.29 m), and the next prediction inherits it. By words against the reference keyframe
    // (ORB-SLAM2's search): independent of how far the camera moved, with fewer matches.
    // Matches the last frame's and the reference keyframe's points within `radius` of where
    // `pose` projects them; the optimized pose's inliers (0 with too few matches).
    auto search_around = [&](const Eigen::Isometry3d& pose, float radius) {
      frame.T_cam_world = pose;
      std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
      int matches = MatchByProjection(frame, *s.last_frame, map, context.geometry, radius, options.matcher);
      matches += MatchByProjection(frame, *reference, map, context.geometry, radius, options.matcher);
      return matches >= options.min_reference_matches ? OptimizeFramePose(map, context, frame) : 0;
    };
    int inliers = search_around(s.last_frame->T_cam_world, 4 * options.motion_search_radius);
    if (options.vocabulary && !reference->bow_features.empty()) {
      const Eigen::Isometry3d around_last = frame.T_cam_world;
      const std::vector<PointHandle> around_last_points = frame.points;
      frame.T_cam_world = s.last_frame->T_cam_world;
      std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
      ComputeFrameWords(*options.vocabulary, frame);
      const int by_words = MatchByBow(frame, *reference, map, options.matcher, options.reference_bow_ratio);
      const int words_inliers = by_words >= options.min_reference_matches ? OptimizeFramePose(map, context, frame) : 0;
      // Where the two poses place a tenth of the matched points farther apart than the pose
      // optimizer's inlier gate at level 0 (sqrt(chi2_mono) pixels), they cannot share those
      // inliers, and their counts are not comparable: around the wrong pose the wide window still
      // matches the far points, which fit any translation, while the words match fewer points,
      // right ones. Each pose then searches around itself with the motion window, as tracking with
      // a prior does, and the one that finds more wins. The gap is in pixels, so a short focal
      // length shows the same wrong translation as a smaller gap (figures: docs/STATUS.md, the
      // first frame's two poses).
      const float gap = PredictionError(map, context.geometry.camera, around_last, frame, 0.9);
      const double inlier_gate_px = std::sqrt(options.pose.chi2_mono);
      if (words_inliers >= options.min_motion_inliers && inliers >= options.min_motion_inliers &&
          gap > inlier_gate_px) {
        const Eigen::Isometry3d by_words_pose = frame.T_cam_world;
        const int words_around = search_around(by_words_pose, options.motion_search_radius);
        const Eigen::Isometry3d words_pose = frame.T_cam_world;
        const std::vector<PointHandle> words_points = frame.points;
        const int last_around = search_around(around_last, options.motion_search_radius);
        if (words_around > last_around) {
          frame.T_cam_world = words_pose;
          frame.points = words_points;
          inliers = words_around;
        } else {
          inliers = last_around;
        }
      } else if (words_inliers > inliers) {
        inliers = words_inliers;
      } else {
        frame.T_cam_world = around_last;
        frame.points = around_last_points;
      }
    }
    return inliers >= options.min_motion_inliers;
  }

  bool TrackLocalMap(TrackedFrame& frame, int* matches) {
    // Local keyframes: those sharing points with the frame, plus their best neighbours.
    std::unordered_map<KeyFrameHandle, int> votes;
    for (PointHandle p : frame.points) {
      const MapPoint* point = map.points().try_get(p);
      if (!point) continue;
      for (const Observation& o : point->observations) ++votes[o.keyframe];
    }
    if (votes.empty()) return false;
    std::vector<std::pair<KeyFrameHandle, int>> ranked(votes.begin(), votes.end());
    std::sort(ranked.begin(), ranked.end(), Map::StrongerLink);
    std::vector<KeyFrameHandle>& local = s.local_keyframes;
    local.clear();
    std::unordered_set<KeyFrameHandle> in_set;
    for (const auto& [kf, count] : ranked) {
      if (local.size() >= options.max_local_map_keyframes) break;
      if (in_set.insert(kf).second) local.push_back(kf);
    }
    s.reference_keyframe = ranked.front().first;
    const size_t direct = local.size();
    for (size_t i = 0; i < direct && local.size() < options.max_local_map_keyframes; ++i) {
      for (KeyFrameHandle n : map.BestCovisible(local[i], 10)) {
        if (in_set.insert(n).second) local.push_back(n);
        if (local.size() >= options.max_local_map_keyframes) break;
      }
    }
    s.local_points.clear();
    std::unordered_set<PointHandle> seen_points;
    for (KeyFrameHandle kf : local) {
      for (PointHandle p : map.keyframe(kf).points)
        if (!p.is_null() && seen_points.insert(p).second) s.local_points.push_back(p);
    }
    // Points predicted in view count as sightings (none in localization-only mode).
    MatchLocalPoints(frame, map, s.local_points, context.geometry, 1.0f, options.matcher,
                     options.localization_only ? nullptr : &result.visible);
    *matches = MatchedCount(frame);
    int inliers = OptimizeFramePose(map, context, frame);
    // Far fewer inliers than the last frame had: the predicted pose was off (a sudden turn) and the
    // narrow search missed most points. Search again, three times as wide, from the refined pose,
    // before accepting a weak pose (or making a keyframe of it).
    if (inliers >= 3 && inliers < s.last_inliers / 2) {
      const Eigen::Isometry3d refined = frame.T_cam_world;
      const std::vector<PointHandle> kept = frame.points;
      MatchLocalPoints(frame, map, s.local_points, context.geometry, 3.0f, options.matcher, nullptr);
      const int retried = OptimizeFramePose(map, context, frame);
      if (retried > inliers) {
        inliers = retried;
        *matches = MatchedCount(frame);
      } else {
        frame.T_cam_world = refined;
        frame.points = kept;
      }
    }
    if (!options.localization_only)
      for (PointHandle p : frame.points)
        if (!p.is_null()) result.found.push_back(p);
    s.last_inliers = inliers;
    return inliers >= options.min_local_map_inliers;
  }

  // An older keyframe (not one of the revisit_recent_keyframes newest) already views the scene
  // from within revisit_radius of the median depth, its optical axis within revisit_max_angle_deg.
  bool ViewedBefore(const TrackedFrame& frame) const {
    if (options.revisit_radius <= 0 || s.local_keyframes.empty()) return false;
    thread_local std::vector<double> depths;
    depths.clear();
    for (PointHandle p : frame.points)
      if (const MapPoint* point = map.points().try_get(p)) depths.push_back((frame.T_cam_world * point->position).z());
    if (depths.size() < 20) return false;
    std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
    const double radius = options.revisit_radius * depths[depths.size() / 2];
    uint64_t newest = 0;
    for (KeyFrameHandle h : s.local_keyframes)
      if (const KeyFrame* kf = map.keyframes().try_get(h)) newest = std::max(newest, kf->id);
    const Eigen::Isometry3d T_world_cam = frame.T_cam_world.inverse();
    const Eigen::Vector3d axis = T_world_cam.linear().col(2);
    const uint64_t recent = static_cast<uint64_t>(options.revisit_recent_keyframes);
    const double min_cos = std::cos(options.revisit_max_angle_deg * M_PI / 180.0);
    for (KeyFrameHandle h : s.local_keyframes) {
      const KeyFrame* kf = map.keyframes().try_get(h);
      if (!kf || kf->id + recent > newest) continue;
      const Eigen::Isometry3d T_world_kf = kf->T_cam_world.inverse();
      if ((T_world_kf.translation() - T_world_cam.translation()).norm() < radius &&
          T_world_kf.linear().col(2).dot(axis) > min_cos)
        return true;
    }
    return false;
  }

  bool NeedKeyFrame(const TrackedFrame& frame, int inliers, int pending_keyframes) {
    const KeyFrame* reference = map.keyframes().try_get(s.reference_keyframe);
    if (!reference) return true;
    // A young segment's points cannot have 3 observers yet: counting only those would leave the
    // reference empty and no frame would ever look thin (a new monocular segment in a map of
    // older ones never made a keyframe).
    const int min_observations = s.segment_keyframes <= 2 ? 2 : 3;
    int reference_points = 0;
    for (PointHandle p : reference->points) {
      const MapPoint* point = map.points().try_get(p);
      if (point && static_cast<int>(point->observations.size()) >= min_observations) ++reference_points;
    }
    const double close = context.CloseDepth(frame.keypoints.depth);
    int tracked_close = 0, untracked_close = 0;
    for (size_t i = 0; i < frame.size(); ++i) {
      const float d = frame.keypoints.depth[i];
      if (d <= 0 || d >= close) continue;
      if (frame.points[i].is_null())
        ++untracked_close;
      else
        ++tracked_close;
    }
    const bool need_close =
        tracked_close < options.keyframe_close_tracked && untracked_close > options.keyframe_close_untracked;
    const size_t since = frame.index - s.last_keyframe_frame;
    const bool due = since >= static_cast<size_t>(options.min_frames_between_keyframes);
    const bool idle = pending_keyframes == 0 && due;
    const bool timeout = since >= static_cast<size_t>(options.max_frames_between_keyframes);
    const bool weak = !monocular() && (inliers < options.keyframe_weak_ratio * reference_points || need_close);
    const double ratio = monocular() ? options.keyframe_track_ratio_mono : options.keyframe_track_ratio;
    // With depth, a frame that kept under keyframe_fading_ratio of the most points a frame tracked
    // since the last keyframe is thin too. The two rules above miss a keyframe whose view is new:
    // its points have one or two observers (the reference count only takes points seen by three),
    // and where nothing lies nearer than the close depth the close rule never fires, so tracking
    // could fade until it was lost with no keyframe made (docs/STATUS.md, "SLAM core").
    const bool faded = !monocular() && inliers < options.keyframe_fading_ratio * s.keyframe_peak_inliers;
    const bool thin =
        (inliers < ratio * reference_points || need_close || faded) && inliers > options.keyframe_min_inliers;
    // Busy mapping with tracking fading (a monocular frame keeping few of the reference keyframe's
    // points, keyframe_fading_ratio): ask local mapping to finish early.
    const bool fading = monocular() && (inliers < options.keyframe_fading_ratio * reference_points ||
                                        inliers < options.keyframe_fading_inliers);
    const bool wanted = thin && !idle && (timeout || weak || fading);
    // Monocular keyframes wait for idle mapping (ORB-SLAM2's rule), except a fading frame: one frame
    // later its matches may be gone (KITTI 07 with mapping behind and the cores shared: 111, 71, 42
    // inliers, then lost). It is queued like a weak stereo frame, and tracking waits for mapping
    // to take it. While mapping keeps up (waiting or inline) the queue is empty and nothing changes.
    const bool make = (timeout || idle || weak || (fading && due)) && thin;
    // A revisit with healthy tracking makes no keyframe (the geometric test only runs when one
    // would otherwise be made or asked for).
    if ((wanted || make) && inliers >= options.revisit_healthy_ratio * reference_points &&
        tracked_close >= options.revisit_healthy_close && ViewedBefore(frame)) {
      result.keyframe_wanted = false;
      return false;
    }
    result.keyframe_wanted = wanted;
    if (!make) return false;
    return idle || pending_keyframes < 3;
  }
};

}  // namespace

const char* TrackingStateName(TrackingState state) {
  switch (state) {
    case TrackingState::kNotInitialized:
      return "not_initialized";
    case TrackingState::kOk:
      return "ok";
    case TrackingState::kLost:
      return "lost";
  }
  return "unknown";
}

int OptimizeFramePose(const Map& map, const SystemContext& context, TrackedFrame& frame) {
  const CameraGeometry& geometry = context.geometry;
  std::vector<PoseObservation> observations;
  std::vector<uint32_t> index;
  const double far_depth = context.stereo_depth.FarDepth(frame.keypoints.depth);
  for (uint32_t i = 0; i < frame.size(); ++i) {
    const PointHandle p = frame.points[i];
    if (p.is_null()) continue;
    const MapPoint* point = map.points().try_get(p);
    if (!point) {
      frame.points[i] = PointHandle::null();
      continue;
    }
    PoseObservation o;
    o.X_world = point->position;
    o.uv = frame.keypoints.uv[i].cast<double>();
    o.right_u = context.stereo_depth.RightU(frame.keypoints.uv[i].x(), frame.keypoints.right_u[i],
                                            frame.keypoints.depth[i], far_depth,
                                            geometry.pyramid.scale[frame.keypoints.octave[i]]);
    o.inv_sigma2 = geometry.pyramid.inv_sigma2[frame.keypoints.octave[i]];
    observations.push_back(o);
    index.push_back(i);
  }
  if (observations.size() < 3) return 0;
  const double baseline = geometry.bf / geometry.camera.fx;
  const PoseOptimizationResult result =
      OptimizePose(geometry.camera, baseline, frame.T_cam_world, observations, context.options.pose);
  if (!result.success) return 0;
  frame.T_cam_world = result.T_cam_world;
  std::fill(frame.outlier.begin(), frame.outlier.end(), 0);
  for (size_t k = 0; k < index.size(); ++k)
    if (!result.inlier[k]) frame.points[index[k]] = PointHandle::null();  // outliers leave the frame
  return result.num_inliers;
}

bool ResumeTracking(const Map& map, const SystemContext& context, const AnchoredFramePose& previous,
                    const AnchoredFramePose& last, TrackerState& state) {
  const KeyFrame* reference = map.keyframes().try_get(last.reference);
  if (!reference) return false;
  TrackedFrame frame;
  frame.index = reference->frame_index;
  frame.t_ns = last.t_ns;
  frame.keypoints.resize(reference->size());
  frame.keypoints.uv = reference->uv.vector();
  frame.keypoints.angle = reference->angle.vector();
  frame.keypoints.octave = reference->octave.vector();
  frame.keypoints.descriptor = reference->descriptor.vector();
  frame.keypoints.right_u = reference->right_u.vector();
  frame.keypoints.depth = reference->depth.vector();
  frame.Prepare(context.calibration.camera.width, context.calibration.camera.height);
  frame.points = reference->points;
  frame.T_cam_world = last.T_cam_ref.isometry() * reference->T_cam_world;
  frame.has_pose = true;
  state.velocity = last.T_cam_world.isometry() * previous.T_cam_world.isometry().inverse();
  state.velocity_dt_ns = last.t_ns - previous.t_ns;
  state.last_frame = std::move(frame);
  state.reference_keyframe = last.reference;
  state.local_keyframes = {last.reference};
  state.last_inliers = 0;
  state.lost_frames = 0;
  state.state = TrackingState::kOk;
  return true;
}

std::optional<KeyFrameHandle> Relocalize(const Map& map, const KeyFrameDatabase& database, const SystemContext& context,
                                         TrackedFrame& frame) {
  const SlamOptions& options = context.options;
  if (!options.vocabulary || database.size() == 0) return std::nullopt;
  ComputeFrameWords(*options.vocabulary, frame);
  std::vector<PlaceCandidate> candidates = database.DetectRelocalizationCandidates(map, frame.bow);
  const size_t most = static_cast<size_t>(options.relocalization_candidates);
  if (candidates.size() > most) candidates.resize(most);
  const PinholeCamera& cam = context.geometry.camera;
  const cv::Matx33d K(cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
  for (const PlaceCandidate& c : candidates) {
    const KeyFrame* kf = map.keyframes().try_get(c.keyframe);
    if (!kf) continue;
    std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
    if (MatchByBow(frame, *kf, map, options.matcher, 0.75f) < options.relocalization_min_bow_matches) continue;
    std::vector<cv::Point3d> object;
    std::vector<cv::Point2d> image;
    std::vector<uint32_t> index;
    for (uint32_t i = 0; i < frame.size(); ++i) {
      const MapPoint* point = map.points().try_get(frame.points[i]);
      if (!point) continue;
      object.emplace_back(point->position.x(), point->position.y(), point->position.z());
      image.emplace_back(frame.keypoints.uv[i].x(), frame.keypoints.uv[i].y());
      index.push_back(i);
    }
    cv::Mat rvec, tvec;
    std::vector<int> inliers;
    const bool solved =
        cv::solvePnPRansac(object, image, K, cv::noArray(), rvec, tvec, false, options.relocalization_ransac_iterations,
                           options.relocalization_ransac_px, 0.99, inliers, cv::SOLVEPNP_EPNP);
    if (!solved || static_cast<int>(inliers.size()) < options.relocalization_min_pnp_inliers) continue;
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
    int good = OptimizeFramePose(map, context, frame);
    if (good < 10) continue;
    if (good < 50) {
      MatchByProjection(frame, *kf, map, context.geometry, 10.0f, options.matcher);
      good = OptimizeFramePose(map, context, frame);
    }
    if (good < 50) continue;
    return c.keyframe;
  }
  std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
  return std::nullopt;
}

TrackResult TrackFrame(const Map& map, const KeyFrameDatabase& database, const SystemContext& context, TrackerState& s,
                       TrackedFrame& frame, int pending_keyframes) {
  TrackResult result;
  FrameReport& report = result.report;
  report.index = frame.index;
  report.t_ns = frame.t_ns;
  report.features = static_cast<int>(frame.size());
  for (float d : frame.keypoints.depth) report.stereo_points += d > 0 ? 1 : 0;
  const SlamOptions& options = context.options;
  Tracking t{map, database, context, options, s, result};
  const bool monocular = context.monocular();

  bool ok = false;
  int matches = 0;
  if (s.state == TrackingState::kNotInitialized) {
    ok = monocular ? t.PlanMonocularInitialize(frame) : t.PlanInitialize(frame);
    result.map_keyframe = ok;
  } else {
    bool relocalizing = s.state == TrackingState::kLost;
    if (s.force_lost) {
      s.force_lost = false;
      relocalizing = true;
      s.velocity.reset();
    }
    const std::optional<Eigen::Isometry3d> prediction = PredictedPose(s, frame.t_ns, context.calibration.frame_rate_hz);
    if (!relocalizing) ok = t.TrackWithMotion(frame, prediction) || t.TrackReferenceKeyFrame(frame);
    if (!ok && options.vocabulary) {
      const std::optional<KeyFrameHandle> found = Relocalize(map, database, context, frame);
      if (found) s.reference_keyframe = *found;
      ok = found.has_value();
      report.relocalized = ok;
    }
    const bool have_prediction = prediction.has_value();
    const Eigen::Isometry3d predicted = prediction.value_or(Eigen::Isometry3d::Identity());
    if (ok) ok = t.TrackLocalMap(frame, &matches);
    // A relocalized frame's pose was found without the prediction: its distance says nothing of
    // how well the motion is predicted.
    if (ok && have_prediction && !report.relocalized) {
      const float error = PredictionError(map, context.geometry.camera, predicted, frame);
      s.prediction_error_px = std::max(error, 0.5f * s.prediction_error_px);
    }
    if (!ok) report.relocalized = false;
    if (!ok && ((options.vocabulary && ++s.lost_frames <= options.relocalization_frames) || !s.allow_new_segments ||
                (!monocular && !s.last_frame))) {
      // Lost: relocalize in the same map on the coming frames before starting anew.
      s.state = TrackingState::kLost;
    } else if (!ok && monocular) {
      // Lost without depth: a new two-view initialization starts a new map segment.
      report.reinitialized = true;
      s.lost_frames = 0;
      s.state = TrackingState::kNotInitialized;
      s.velocity.reset();
      s.init_frame.reset();
      s.last_frame.reset();
    } else if (!ok) {
      // Lost: start a new map segment at the predicted pose so the trajectory continues.
      report.reinitialized = true;
      s.lost_frames = 0;
      s.state = TrackingState::kOk;
      frame.T_cam_world = prediction.value_or(s.last_frame->T_cam_world);
      std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
      const Eigen::Isometry3d T = frame.T_cam_world;
      if (t.PlanInitialize(frame)) {
        frame.T_cam_world = T;
        result.map_keyframe = true;
      }
      s.velocity.reset();
    } else {
      s.lost_frames = 0;
      if (report.relocalized) s.velocity.reset();
      const int inliers = MatchedCount(frame);
      report.inliers = inliers;
      const bool need_keyframe = !options.localization_only && t.NeedKeyFrame(frame, inliers, pending_keyframes);
      s.keyframe_peak_inliers = std::max(s.keyframe_peak_inliers, inliers);  // a keyframe made resets it
      if (need_keyframe) {
        result.insert = TrackResult::Insert::kKeyFrame;
        result.map_keyframe = true;
      }
    }
  }
  report.matches = matches;
  result.ok = ok;
  return result;
}

std::optional<AnchoredFramePose> FinishFrame(const Map& map, TrackerState& s, TrackedFrame&& frame, TrackResult& result,
                                             const InsertedTwoView& inserted,
                                             std::optional<KeyFrameHandle>* new_keyframe) {
  new_keyframe->reset();
  FrameReport& report = result.report;
  // The keyframes mapping made become tracking's reference.
  switch (result.insert) {
    case TrackResult::Insert::kNone:
      break;
    case TrackResult::Insert::kKeyFrame:
    case TrackResult::Insert::kFirstKeyFrame:
      s.reference_keyframe = inserted.first;
      s.last_keyframe_frame = frame.index;
      s.keyframe_peak_inliers = 0;
      ++s.segment_keyframes;
      if (result.insert == TrackResult::Insert::kFirstKeyFrame) {
        if (s.first_keyframe.is_null()) s.first_keyframe = inserted.first;
        s.local_keyframes = {inserted.first};
      }
      break;
    case TrackResult::Insert::kTwoView:
      s.reference_keyframe = inserted.second;
      s.last_keyframe_frame = frame.index;
      s.keyframe_peak_inliers = 0;
      s.segment_keyframes += 2;
      if (s.first_keyframe.is_null()) s.first_keyframe = inserted.first;
      s.local_keyframes = {inserted.first, inserted.second};
      break;
  }
  if (result.map_keyframe) *new_keyframe = s.reference_keyframe;

  const bool ok = result.ok;
  if (s.state == TrackingState::kLost && !ok) {
    report.state = TrackingState::kLost;
  } else if (s.state == TrackingState::kNotInitialized && !ok) {
    report.state = report.reinitialized ? TrackingState::kLost : TrackingState::kNotInitialized;
  } else {
    report.state = report.reinitialized ? TrackingState::kLost : TrackingState::kOk;
    s.state = TrackingState::kOk;
    if (s.last_frame && !report.reinitialized && !report.relocalized) {
      s.velocity = frame.T_cam_world * s.last_frame->T_cam_world.inverse();
      s.velocity_dt_ns = frame.t_ns - s.last_frame->t_ns;
    }
    AnchoredFramePose pose;
    pose.t_ns = frame.t_ns;
    pose.reference = s.reference_keyframe;
    pose.T_cam_world = CompactPose(frame.T_cam_world);
    pose.T_cam_ref = CompactPose(frame.T_cam_world * map.keyframe(s.reference_keyframe).T_cam_world.inverse());
    report.T_world_cam = frame.T_cam_world.inverse();
    frame.has_pose = true;
    s.last_frame = std::move(frame);
    return pose;
  }
  return std::nullopt;
}

}  // namespace flatslam
