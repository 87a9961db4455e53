#include "slam/slam.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <cstdio>
#include <unordered_map>
#include <unordered_set>

#include <tbb/parallel_invoke.h>

#include "core/error.h"
#include "core/requirements.h"
#include "geometry/geometry.h"
#include "place/vocabulary.h"

namespace flatslam {
namespace {

double MsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

// Back-projects keypoint i of a frame with depth into the world.
Eigen::Vector3d Unproject(const PinholeCamera& cam, const Eigen::Isometry3d& T_cam_world, const Eigen::Vector2f& uv,
                          float depth) {
  const Eigen::Vector3d Xc((uv.x() - cam.cx) / cam.fx * depth, (uv.y() - cam.cy) / cam.fy * depth, depth);
  return T_cam_world.inverse() * Xc;
}

// Keypoints of the frame matched to a map point.
int MatchedCount(const TrackedFrame& frame) {
  return static_cast<int>(
      std::count_if(frame.points.begin(), frame.points.end(), [](PointHandle p) { return !p.is_null(); }));
}

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

std::string SlamOptions::Problem() const {
  OrbOptions orb_checked = orb;
  if (orb_checked.features == 0) orb_checked.features = 1;  // 0 = derived from the camera
  Requirements r;
  r.Nested("orb", orb_checked.Problem());
  r.Nested("stereo", stereo.Problem());
  r.Nested("matcher", matcher.Problem());
  r.Nested("pose", pose.Problem());
  r.Nested("bundle_adjustment", bundle_adjustment.Problem());
  FLATSLAM_REQUIRE(r, rgbd_virtual_baseline_m > 0);
  FLATSLAM_REQUIRE(r, close_depth_baselines > 0);
  FLATSLAM_REQUIRE(r, far_stereo_baselines >= 0);
  FLATSLAM_REQUIRE(r, min_init_points > 0);
  FLATSLAM_REQUIRE(r, min_motion_inliers > 0);
  FLATSLAM_REQUIRE(r, min_local_map_inliers > 0);
  FLATSLAM_REQUIRE(r, motion_search_radius > 0);
  FLATSLAM_REQUIRE(r, max_frames_between_keyframes >= 0);
  FLATSLAM_REQUIRE(r, min_frames_between_keyframes >= -1);
  FLATSLAM_REQUIRE(r, local_keyframes > 0);
  FLATSLAM_REQUIRE(r, min_parallax_deg >= 0 && min_parallax_deg < 90);
  FLATSLAM_REQUIRE(r, redundant_keyframe_ratio > 0 && redundant_keyframe_ratio <= 1);
  FLATSLAM_REQUIRE(r, revisit_radius >= 0);
  FLATSLAM_REQUIRE(r, relocalization_frames >= 0);
  FLATSLAM_REQUIRE(r, loop_consistency >= 1);
  FLATSLAM_REQUIRE(r, min_loop_matches >= 3);
  return r.first();
}

int DerivedFeatureBudget(const PinholeCamera& camera, double frame_rate_hz) {
  // One feature per 300 px^2 keeps the keypoints per FAST cell the same at every resolution (the
  // density of ORB-SLAM's budgets for 640x480 and 752x480 cameras: 1000 and 1200). Below 20 Hz the
  // scene moves further between frames and fewer keypoints survive from one frame to the next:
  // the budget grows with sqrt(20 / rate), halfway (in log terms) between no growth and growth
  // with the image motion per frame.
  const double rate = frame_rate_hz > 0 ? frame_rate_hz : 20.0;
  const double raw = static_cast<double>(camera.width) * camera.height / 300.0 * std::sqrt(std::max(1.0, 20.0 / rate));
  // Nearest value of the 1-1.2-1.5-2-2.5-3-4-5-6-8 series (in log terms), so that cameras of
  // nearly the same size share a budget.
  static constexpr double kSeries[] = {1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10};
  const double decade = std::pow(10.0, std::floor(std::log10(std::max(raw, 1.0))));
  double best = decade;
  for (double m : kSeries)
    if (std::abs(std::log(m * decade / raw)) < std::abs(std::log(best / raw))) best = m * decade;
  return static_cast<int>(std::clamp(std::lround(best), 500L, 8000L));
}

SlamOptions ResolvedOptions(const SlamOptions& options, const Calibration& calibration,
                            std::vector<DerivedOption>* derived) {
  SlamOptions o = options;
  const bool mono = calibration.sensor == Sensor::kMonocular;
  const PinholeCamera& cam = calibration.camera;
  auto note = [&](const char* key, std::string rule) {
    if (derived) derived->push_back({key, std::move(rule)});
  };
  char text[256];
  const double rate = calibration.frame_rate_hz;
  if (o.orb.features == 0) {
    o.orb.features = DerivedFeatureBudget(cam, rate);
    std::snprintf(text, sizeof(text),
                  "one feature per 300 px^2 of %dx%d, x sqrt(20 Hz / %.3g Hz) below 20 Hz, rounded to the "
                  "1-1.2-1.5-2-2.5-3-4-5-6-8 series",
                  cam.width, cam.height, rate > 0 ? rate : 20.0);
    note("orb.features", text);
  }
  if (o.max_frames_between_keyframes == 0) {
    o.max_frames_between_keyframes = rate > 0 ? static_cast<int>(std::lround(rate)) : 10;
    note("max_frames_between_keyframes",
         rate > 0 ? "one second of frames at the camera's frame rate" : "10 frames: the frame rate is unknown");
  }
  if (mono) {
    o.motion_search_radius = o.mono_search_radius;
    note("motion_search_radius", "monocular: mono_search_radius (no depth to predict the right image)");
  }
  if (o.min_frames_between_keyframes < 0) {
    o.min_frames_between_keyframes = mono ? 2 : 0;
    note("min_frames_between_keyframes", mono ? "monocular: 2, forward motion thins tracked points every frame"
                                              : "with depth: 0, an idle local mapping takes any keyframe");
  }
  if (o.min_parallax_deg == 0) {
    o.min_parallax_deg = mono ? 2.0 : 1.146;
    note("min_parallax_deg", mono ? "monocular: 2 degrees, depth within about 4% at a pixel of noise"
                                  : "with depth: 1.146 degrees; close points take the measured depth");
  }
  return o;
}

Slam::Slam(const Calibration& calibration, const SlamOptions& options)
    : calibration_(calibration),
      options_(ResolvedOptions(options, calibration)),
      extractor_(options_.orb),
      rng_(options.seed),
      database_(options.vocabulary ? options.vocabulary->word_count() : 0),
      loop_rng_(options.seed + 1) {
  const std::string problem = options_.Problem();
  FLATSLAM_CHECK(problem.empty(), "invalid SLAM options: ", problem, " does not hold");
  FLATSLAM_CHECK(calibration_.camera.valid(), "invalid camera calibration");
  FLATSLAM_CHECK(calibration_.sensor != Sensor::kStereo || calibration_.baseline_m > 0,
                 "stereo calibration without a baseline");
  geometry_ = CameraGeometry::FromCalibration(calibration_, options_.rgbd_virtual_baseline_m, extractor_.scales());
  if (options_.localization_only) allow_new_segments_ = false;
  map_scales_.scale_factor = geometry_.pyramid.scale_factor;
  map_scales_.levels = geometry_.pyramid.levels;
  stereo_depth_ = StereoDepthRule::ForRig(calibration_.sensor == Sensor::kStereo, calibration_.baseline_m,
                                          options_.far_stereo_baselines);
}

double Slam::CloseDepth() const {
  return monocular() ? 0.0 : options_.close_depth_baselines * geometry_.bf / geometry_.camera.fx;
}

void Slam::Extract(const Frame& frame, TrackedFrame* out) const {
  const PinholeCamera& cam = calibration_.camera;
  FLATSLAM_CHECK(frame.left.cols == cam.width && frame.left.rows == cam.height, "frame ", frame.index, " is ",
                 frame.left.cols, "x", frame.left.rows, ", calibration says ", cam.width, "x", cam.height);
  out->index = frame.index;
  out->t_ns = frame.t_ns;
  // Pooled pyramids: their levels are not reallocated per frame.
  const auto left_pyramid = pyramids_.Acquire();
  if (calibration_.sensor == Sensor::kStereo) {
    FLATSLAM_CHECK(!frame.right.empty(), "frame ", frame.index, " has no right image");
    Keypoints right;
    const auto right_pyramid = pyramids_.Acquire();
    tbb::parallel_invoke([&] { extractor_.Extract(frame.left, &out->keypoints, left_pyramid.get()); },
                         [&] { extractor_.Extract(frame.right, &right, right_pyramid.get()); });
    MatchStereo(right, *left_pyramid, *right_pyramid, extractor_.scales(), cam.fx, calibration_.baseline_m,
                options_.stereo, &out->keypoints);
    right_pyramid->levels[0].release();  // level 0 shares the input image: do not keep it alive
  } else {
    FLATSLAM_CHECK(calibration_.sensor == Sensor::kMonocular || !frame.depth.empty(), "frame ", frame.index,
                   " has no depth image");
    extractor_.Extract(frame.left, &out->keypoints, left_pyramid.get());
    if (calibration_.sensor == Sensor::kRgbd)
      DepthFromImage(frame.depth, cam.fx, options_.rgbd_virtual_baseline_m, &out->keypoints);
  }
  left_pyramid->levels[0].release();
  out->Prepare(cam.width, cam.height);
}

FrameReport Slam::Track(TrackedFrame&& frame, std::optional<KeyFrameHandle>* new_keyframe) {
  const auto start = std::chrono::steady_clock::now();
  new_keyframe->reset();
  FrameReport report;
  report.index = frame.index;
  report.t_ns = frame.t_ns;
  report.features = static_cast<int>(frame.size());
  for (float d : frame.keypoints.depth) report.stereo_points += d > 0 ? 1 : 0;

  std::lock_guard<std::mutex> lock(map_mutex_);
  next_frame_ = frame.index + 1;
  bool ok = false;
  int matches = 0;
  if (state_ == TrackingState::kNotInitialized) {
    ok = monocular() ? InitializeMonocular(frame) : Initialize(frame);
    if (ok) *new_keyframe = reference_keyframe_;
  } else {
    if (map_corrected_ && last_frame_ && !frame_poses_.empty()) {
      // A loop correction or global BA moved the map: the last frame follows its reference keyframe.
      last_frame_->T_cam_world = ResolveFramePose(frame_poses_.back());
      map_corrected_ = false;
    }
    bool relocalizing = state_ == TrackingState::kLost;
    if (force_lost_) {
      force_lost_ = false;
      relocalizing = true;
      velocity_.reset();
    }
    if (!relocalizing) ok = TrackWithMotion(frame) || TrackReferenceKeyFrame(frame);
    if (!ok && options_.vocabulary) {
      ok = Relocalize(frame);
      report.relocalized = ok;
    }
    if (ok) ok = TrackLocalMap(frame, &matches);
    if (!ok) report.relocalized = false;
    if (!ok && ((options_.vocabulary && ++lost_frames_ <= options_.relocalization_frames) || !allow_new_segments_ ||
                (!monocular() && !last_frame_))) {
      // Lost: relocalize in the same map on the coming frames before starting anew.
      state_ = TrackingState::kLost;
    } else if (!ok && monocular()) {
      // Lost without depth: a new two-view initialization starts a new map segment.
      report.reinitialized = true;
      lost_frames_ = 0;
      state_ = TrackingState::kNotInitialized;
      velocity_.reset();
      init_frame_.reset();
      last_frame_.reset();
    } else if (!ok) {
      // Lost: start a new map segment at the predicted pose so the trajectory continues.
      report.reinitialized = true;
      lost_frames_ = 0;
      state_ = TrackingState::kOk;
      frame.T_cam_world = velocity_ ? (*velocity_ * last_frame_->T_cam_world) : last_frame_->T_cam_world;
      std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
      const Eigen::Isometry3d T = frame.T_cam_world;
      if (Initialize(frame)) {
        frame.T_cam_world = T;
        *new_keyframe = reference_keyframe_;
      }
      velocity_.reset();
    } else {
      lost_frames_ = 0;
      if (report.relocalized) velocity_.reset();
      const int inliers = MatchedCount(frame);
      report.inliers = inliers;
      if (!options_.localization_only && NeedKeyFrame(frame, inliers)) *new_keyframe = CreateKeyFrame(frame);
    }
  }

  report.matches = matches;
  if (state_ == TrackingState::kLost && !ok) {
    report.state = TrackingState::kLost;
  } else if (state_ == TrackingState::kNotInitialized && !ok) {
    report.state = report.reinitialized ? TrackingState::kLost : TrackingState::kNotInitialized;
  } else {
    report.state = report.reinitialized ? TrackingState::kLost : TrackingState::kOk;
    state_ = TrackingState::kOk;
    if (last_frame_ && !report.reinitialized && !report.relocalized)
      velocity_ = frame.T_cam_world * last_frame_->T_cam_world.inverse();
    FramePose pose;
    pose.t_ns = frame.t_ns;
    pose.reference = reference_keyframe_;
    pose.T_cam_world = CompactPose(frame.T_cam_world);
    pose.T_cam_ref = CompactPose(frame.T_cam_world * map_.keyframe(reference_keyframe_).T_cam_world.inverse());
    frame_poses_.push_back(pose);
    report.T_world_cam = frame.T_cam_world.inverse();
    frame.has_pose = true;
    last_frame_ = std::move(frame);
  }
  report.keyframe = new_keyframe->has_value();
  report.map_keyframes = map_.keyframes().size();
  report.map_points = map_.points().size();
  if (report.keyframe) ++pending_keyframes_;
  report.track_ms = MsSince(start);
  return report;
}

bool Slam::Initialize(TrackedFrame& frame) {
  if (std::count_if(frame.keypoints.depth.begin(), frame.keypoints.depth.end(), [](float d) { return d > 0; }) <
      options_.min_init_points)
    return false;
  if (first_keyframe_.is_null()) frame.T_cam_world = Eigen::Isometry3d::Identity();
  std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
  segment_keyframes_ = 0;
  const KeyFrameHandle kf = CreateKeyFrame(frame, /*all_depth_points=*/true);
  if (first_keyframe_.is_null()) first_keyframe_ = kf;
  local_keyframes_ = {kf};
  return true;
}

bool Slam::InitializeMonocular(TrackedFrame& frame) {
  if (!init_frame_ || static_cast<int>(frame.size()) <= options_.min_init_matches) {
    if (static_cast<int>(frame.size()) > options_.min_init_matches) init_frame_ = frame;
    return false;
  }
  const auto pairs = MatchForInitialization(*init_frame_, frame, 100.0f, options_.matcher);
  if (static_cast<int>(pairs.size()) < options_.min_init_matches) {
    init_frame_ = frame;  // too little overlap left: start again from this frame
    return false;
  }
  std::vector<Eigen::Vector2d> px1, px2;
  for (const auto& [i1, i2] : pairs) {
    px1.push_back(init_frame_->keypoints.uv[i1].cast<double>());
    px2.push_back(frame.keypoints.uv[i2].cast<double>());
  }
  const std::optional<TwoViewResult> two_view = InitializeTwoView(px1, px2, geometry_.camera, TwoViewOptions{}, rng_);
  if (!two_view) return false;

  // Two keyframes: the first frame at the origin (or the last pose of a previous segment), the
  // current one at the recovered motion; points are in first-frame coordinates.
  const Eigen::Isometry3d T_first_world =
      first_keyframe_.is_null() ? Eigen::Isometry3d::Identity() : init_frame_->T_cam_world;
  TrackedFrame& first = *init_frame_;
  first.T_cam_world = T_first_world;
  std::fill(first.points.begin(), first.points.end(), PointHandle::null());
  std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
  frame.T_cam_world = two_view->T_2_1 * T_first_world;
  segment_keyframes_ = 0;
  const KeyFrameHandle kf1 = CreateKeyFrame(first);
  const KeyFrameHandle kf2 = CreateKeyFrame(frame);
  const Eigen::Isometry3d T_world_first = T_first_world.inverse();
  int created = 0;
  for (size_t k = 0; k < pairs.size(); ++k) {
    if (!two_view->triangulated[k]) continue;
    const PointHandle p = map_.AddPoint(T_world_first * two_view->points[k], kf1);
    map_.AddObservation(p, kf1, pairs[k].first);
    map_.AddObservation(p, kf2, pairs[k].second);
    map_.UpdatePointStats(p, map_scales_);
    frame.points[pairs[k].second] = p;
    ++created;
  }
  map_.UpdateCovisibility(kf1);
  map_.UpdateCovisibility(kf2);
  if (first_keyframe_.is_null()) first_keyframe_ = kf1;
  reference_keyframe_ = kf2;
  local_keyframes_ = {kf1, kf2};
  velocity_.reset();
  init_frame_.reset();
  return created >= options_.min_init_matches / 2;
}

int Slam::OptimizeFramePose(TrackedFrame& frame) {
  std::vector<PoseObservation> observations;
  std::vector<uint32_t> index;
  const double far_depth = stereo_depth_.FarDepth(frame.keypoints.depth);
  for (uint32_t i = 0; i < frame.size(); ++i) {
    const PointHandle p = frame.points[i];
    if (p.is_null()) continue;
    const MapPoint* point = map_.points().try_get(p);
    if (!point) {
      frame.points[i] = PointHandle::null();
      continue;
    }
    PoseObservation o;
    o.X_world = point->position;
    o.uv = frame.keypoints.uv[i].cast<double>();
    o.right_u = StereoDepthRule::RightU(frame.keypoints.right_u[i], frame.keypoints.depth[i], far_depth);
    o.inv_sigma2 = geometry_.pyramid.inv_sigma2[frame.keypoints.octave[i]];
    observations.push_back(o);
    index.push_back(i);
  }
  if (observations.size() < 3) return 0;
  const double baseline = geometry_.bf / geometry_.camera.fx;
  const PoseOptimizationResult result =
      OptimizePose(geometry_.camera, baseline, frame.T_cam_world, observations, options_.pose);
  if (!result.success) return 0;
  frame.T_cam_world = result.T_cam_world;
  std::fill(frame.outlier.begin(), frame.outlier.end(), 0);
  for (size_t k = 0; k < index.size(); ++k) {
    if (!result.inlier[k]) {
      frame.points[index[k]] = PointHandle::null();  // outliers are dropped from the frame
    }
  }
  return result.num_inliers;
}

bool Slam::TrackWithMotion(TrackedFrame& frame) {
  if (!velocity_ || !last_frame_) return false;
  frame.T_cam_world = *velocity_ * last_frame_->T_cam_world;
  std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
  int matches =
      MatchByProjection(frame, *last_frame_, map_, geometry_, options_.motion_search_radius, options_.matcher);
  if (matches < 20) {
    std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
    matches =
        MatchByProjection(frame, *last_frame_, map_, geometry_, 2 * options_.motion_search_radius, options_.matcher);
  }
  if (matches < 20) return false;
  // A pose carried by a sliver of the last frame's matches is more likely wrong than right:
  // the reference keyframe search (wider, without the motion prior) gets a say.
  const int inliers = OptimizeFramePose(frame);
  return inliers >= options_.min_motion_inliers && inliers * 8 >= last_inliers_;
}

bool Slam::TrackReferenceKeyFrame(TrackedFrame& frame) {
  if (!last_frame_) return false;
  const KeyFrame* reference = map_.keyframes().try_get(reference_keyframe_);
  if (!reference) return false;
  // Without a motion prior, search wide around the last pose.
  frame.T_cam_world = last_frame_->T_cam_world;
  std::fill(frame.points.begin(), frame.points.end(), PointHandle::null());
  int matches =
      MatchByProjection(frame, *last_frame_, map_, geometry_, 4 * options_.motion_search_radius, options_.matcher);
  matches += MatchByProjection(frame, *reference, map_, geometry_, 4 * options_.motion_search_radius, options_.matcher);
  if (matches < 15) return false;
  return OptimizeFramePose(frame) >= options_.min_motion_inliers;
}

bool Slam::TrackLocalMap(TrackedFrame& frame, int* matches) {
  // Local keyframes: those sharing points with the frame, plus their best neighbours.
  std::unordered_map<KeyFrameHandle, int> votes;
  for (PointHandle p : frame.points) {
    const MapPoint* point = map_.points().try_get(p);
    if (!point) continue;
    for (const Observation& o : point->observations) ++votes[o.keyframe];
  }
  if (votes.empty()) return false;
  std::vector<std::pair<KeyFrameHandle, int>> ranked(votes.begin(), votes.end());
  std::sort(ranked.begin(), ranked.end(), [](const auto& a, const auto& b) {
    return a.second != b.second ? a.second > b.second : a.first < b.first;
  });
  local_keyframes_.clear();
  std::unordered_set<KeyFrameHandle> in_set;
  for (const auto& [kf, count] : ranked) {
    if (local_keyframes_.size() >= options_.max_local_map_keyframes) break;
    if (in_set.insert(kf).second) local_keyframes_.push_back(kf);
  }
  reference_keyframe_ = ranked.front().first;
  const size_t direct = local_keyframes_.size();
  for (size_t i = 0; i < direct && local_keyframes_.size() < options_.max_local_map_keyframes; ++i) {
    for (KeyFrameHandle n : map_.BestCovisible(local_keyframes_[i], 10)) {
      if (in_set.insert(n).second) local_keyframes_.push_back(n);
      if (local_keyframes_.size() >= options_.max_local_map_keyframes) break;
    }
  }
  local_points_.clear();
  std::unordered_set<PointHandle> seen_points;
  for (KeyFrameHandle kf : local_keyframes_) {
    for (PointHandle p : map_.keyframe(kf).points)
      if (!p.is_null() && seen_points.insert(p).second) local_points_.push_back(p);
  }
  std::vector<PointHandle> visible;
  MatchLocalPoints(frame, map_, local_points_, geometry_, 1.0f, options_.matcher, &visible);
  if (!options_.localization_only)
    for (PointHandle p : visible)
      if (MapPoint* point = map_.points().try_get(p)) ++point->visible;
  *matches = MatchedCount(frame);
  int inliers = OptimizeFramePose(frame);
  // Far fewer inliers than the last frame had: the predicted pose was off (a sudden turn) and the
  // narrow search missed most points. Search again, three times as wide, from the refined pose,
  // before accepting a weak pose (or making a keyframe of it).
  if (inliers >= 3 && inliers < last_inliers_ / 2) {
    const Eigen::Isometry3d refined = frame.T_cam_world;
    const std::vector<PointHandle> kept = frame.points;
    MatchLocalPoints(frame, map_, local_points_, geometry_, 3.0f, options_.matcher, nullptr);
    const int retried = OptimizeFramePose(frame);
    if (retried > inliers) {
      inliers = retried;
      *matches = MatchedCount(frame);
    } else {
      frame.T_cam_world = refined;
      frame.points = kept;
    }
  }
  if (!options_.localization_only)
    for (PointHandle p : frame.points)
      if (MapPoint* point = map_.points().try_get(p)) ++point->found;
  last_inliers_ = inliers;
  return inliers >= options_.min_local_map_inliers;
}

bool Slam::NeedKeyFrame(const TrackedFrame& frame, int inliers) const {
  const KeyFrame* reference = map_.keyframes().try_get(reference_keyframe_);
  if (!reference) return true;
  // A young segment's points cannot have 3 observers yet: counting only those would leave the
  // reference empty and no frame would ever look thin (a new monocular segment in a map of
  // older ones never made a keyframe).
  const int min_observations = segment_keyframes_ <= 2 ? 2 : 3;
  int reference_points = 0;
  for (PointHandle p : reference->points) {
    const MapPoint* point = map_.points().try_get(p);
    if (point && static_cast<int>(point->observations.size()) >= min_observations) ++reference_points;
  }
  const double close = CloseDepth();
  int tracked_close = 0, untracked_close = 0;
  for (size_t i = 0; i < frame.size(); ++i) {
    const float d = frame.keypoints.depth[i];
    if (d <= 0 || d >= close) continue;
    if (frame.points[i].is_null())
      ++untracked_close;
    else
      ++tracked_close;
  }
  const bool need_close = tracked_close < 100 && untracked_close > 70;
  const size_t since = frame.index - last_keyframe_frame_;
  const bool idle = pending_keyframes_ == 0 && since >= static_cast<size_t>(options_.min_frames_between_keyframes);
  const bool timeout = since >= static_cast<size_t>(options_.max_frames_between_keyframes);
  const bool weak = !monocular() && (inliers < 0.25 * reference_points || need_close);
  const double ratio = monocular() ? 0.9 : 0.75;
  const bool thin = (inliers < ratio * reference_points || need_close) && inliers > 15;
  // Busy mapping with tracking fading (a monocular frame keeping under half the reference
  // keyframe's points): ask local mapping to finish early.
  const bool fading = monocular() && (inliers < 0.5 * reference_points || inliers < 100);
  const bool wanted = thin && !idle && (timeout || weak || fading);
  const bool make = (timeout || idle || weak) && thin;
  // A revisit with healthy tracking makes no keyframe (the geometric test only runs when one
  // would otherwise be made or asked for).
  if ((wanted || make) && inliers >= 0.5 * reference_points && tracked_close >= 50 && ViewedBefore(frame)) {
    keyframe_wanted_ = false;
    return false;
  }
  keyframe_wanted_ = wanted;
  if (!make) return false;
  return idle || pending_keyframes_ < 3;
}

bool Slam::ViewedBefore(const TrackedFrame& frame) const {
  if (options_.revisit_radius <= 0 || local_keyframes_.empty()) return false;
  thread_local std::vector<double> depths;
  depths.clear();
  for (PointHandle p : frame.points)
    if (const MapPoint* point = map_.points().try_get(p)) depths.push_back((frame.T_cam_world * point->position).z());
  if (depths.size() < 20) return false;
  std::nth_element(depths.begin(), depths.begin() + depths.size() / 2, depths.end());
  const double radius = options_.revisit_radius * depths[depths.size() / 2];
  uint64_t newest = 0;
  for (KeyFrameHandle h : local_keyframes_)
    if (const KeyFrame* kf = map_.keyframes().try_get(h)) newest = std::max(newest, kf->id);
  const Eigen::Isometry3d T_world_cam = frame.T_cam_world.inverse();
  const Eigen::Vector3d axis = T_world_cam.linear().col(2);
  constexpr uint64_t kRecent = 20;
  const double min_cos = std::cos(20.0 * M_PI / 180.0);
  for (KeyFrameHandle h : local_keyframes_) {
    const KeyFrame* kf = map_.keyframes().try_get(h);
    if (!kf || kf->id + kRecent > newest) continue;
    const Eigen::Isometry3d T_world_kf = kf->T_cam_world.inverse();
    if ((T_world_kf.translation() - T_world_cam.translation()).norm() < radius &&
        T_world_kf.linear().col(2).dot(axis) > min_cos)
      return true;
  }
  return false;
}

KeyFrameHandle Slam::CreateKeyFrame(TrackedFrame& frame, bool all_depth_points) {
  KeyFrame kf;
  kf.frame_index = frame.index;
  kf.t_ns = frame.t_ns;
  kf.agent = options_.agent;
  kf.T_cam_world = frame.T_cam_world;
  kf.uv = frame.keypoints.uv;
  kf.right_u = frame.keypoints.right_u;
  kf.depth = frame.keypoints.depth;
  kf.angle = frame.keypoints.angle;
  kf.octave = frame.keypoints.octave;
  kf.descriptor = frame.keypoints.descriptor;
  kf.points.assign(frame.size(), PointHandle::null());
  const KeyFrameHandle h = map_.AddKeyFrame(std::move(kf));
  for (uint32_t i = 0; i < frame.size(); ++i) {
    const PointHandle p = frame.points[i];
    if (p.is_null() || !map_.points().contains(p)) continue;
    const auto& obs = map_.point(p).observations;
    if (std::any_of(obs.begin(), obs.end(), [&](const Observation& o) { return o.keyframe == h; })) continue;
    map_.AddObservation(p, h, i);
  }
  // New points from stereo/RGB-D depth: all close ones, and at least the 100 nearest.
  std::vector<uint32_t> by_depth;
  for (uint32_t i = 0; i < frame.size(); ++i)
    if (frame.keypoints.depth[i] > 0) by_depth.push_back(i);
  std::sort(by_depth.begin(), by_depth.end(),
            [&](uint32_t a, uint32_t b) { return frame.keypoints.depth[a] < frame.keypoints.depth[b]; });
  const double close = all_depth_points ? 1e30 : CloseDepth();
  int considered = 0;
  for (uint32_t i : by_depth) {
    if (frame.keypoints.depth[i] > close && considered > 100) break;
    ++considered;
    if (!frame.points[i].is_null()) continue;
    const PointHandle p = map_.AddPoint(
        Unproject(geometry_.camera, frame.T_cam_world, frame.keypoints.uv[i], frame.keypoints.depth[i]), h);
    map_.AddObservation(p, h, i);
    map_.UpdatePointStats(p, map_scales_);
    frame.points[i] = p;
    recent_points_.push_back(p);
  }
  map_.UpdateCovisibility(h);
  reference_keyframe_ = h;
  last_keyframe_frame_ = frame.index;
  ++segment_keyframes_;
  return h;
}

void Slam::MapKeyFrame(KeyFrameHandle keyframe) {
  std::vector<KeyFrame>& snapshot = mapping_snapshot_;  // [0] = the new keyframe, then its neighbours
  std::vector<KeyFrameHandle> neighbours;
  std::pair<double, double> depth_range;
  uint64_t epoch = 0;
  size_t frame_index = 0;
  struct Done {
    std::atomic<int>& pending;
    ~Done() { --pending; }
  } done{pending_keyframes_};
  auto stage_start = std::chrono::steady_clock::now();
  auto lap = [&stage_start](double* total) {
    const auto now = std::chrono::steady_clock::now();
    *total += std::chrono::duration<double, std::milli>(now - stage_start).count();
    stage_start = now;
  };
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    if (!map_.keyframes().contains(keyframe)) return;
    frame_index = map_.keyframe(keyframe).frame_index;
    for (PointHandle p : map_.keyframe(keyframe).points)
      if (map_.points().contains(p)) map_.UpdatePointStats(p, map_scales_);
    map_.UpdateCovisibility(keyframe);
    CullRecentPoints(keyframe);
    depth_range = SceneDepthRange(keyframe);
    epoch = map_epoch_;
    // Copies of the keyframes to triangulate against, so matching runs without the lock;
    // assigned over the last keyframe's copies, whose buffers they reuse.
    neighbours = map_.BestCovisible(keyframe, options_.local_keyframes);
    snapshot.resize(neighbours.size() + 1);
    snapshot[0] = map_.keyframe(keyframe);
    for (size_t k = 0; k < neighbours.size(); ++k) snapshot[k + 1] = map_.keyframe(neighbours[k]);
  }
  ++mapping_times_.keyframes;
  lap(&mapping_times_.prepare_ms);
  // The words come first: monocular triangulation searches keypoints under the same node.
  if (options_.vocabulary)
    options_.vocabulary->Transform(snapshot[0].descriptor, &snapshot[0].bow, &snapshot[0].bow_features);
  const std::vector<NewPoint> candidates = FindNewPoints(snapshot, neighbours, depth_range);
  BowVector bow = std::move(snapshot[0].bow);
  FeatureVector bow_features = std::move(snapshot[0].bow_features);
  lap(&mapping_times_.triangulate_ms);
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    if (!map_.keyframes().contains(keyframe)) return;
    map_.keyframe(keyframe).bow = std::move(bow);
    map_.keyframe(keyframe).bow_features = std::move(bow_features);
    if (epoch == map_epoch_) AddNewPoints(keyframe, candidates);  // else triangulated in the old frame
    Fuse(keyframe);
    map_.UpdateCovisibility(keyframe);
  }
  lap(&mapping_times_.fuse_ms);
  LocalBundleAdjustment(keyframe);
  lap(&mapping_times_.local_ba_ms);
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    if (map_.keyframes().contains(keyframe)) CullKeyFrames(keyframe);
  }
  lap(&mapping_times_.cull_ms);
  // A failed loop correction costs that loop, not the session: it becomes a warning and the next
  // keyframes are searched as usual.
  try {
    DetectAndCloseLoop(keyframe);
  } catch (const std::exception& e) {
    consistent_groups_.clear();
    Warn("loop closing failed at the keyframe of frame " + std::to_string(frame_index) +
         ", the session goes on without this loop: " + e.what());
  }
  lap(&mapping_times_.place_ms);
}

void Slam::CullRecentPoints(KeyFrameHandle current) {
  const uint64_t current_id = map_.keyframe(current).id;
  const size_t min_observations = monocular() ? 2 : 3;
  std::vector<PointHandle> keep;
  for (PointHandle p : recent_points_) {
    MapPoint* point = map_.points().try_get(p);
    if (!point) continue;
    const uint64_t age = current_id - std::min(current_id, point->first_keyframe_id);
    if (point->found_ratio() < 0.25f || (age >= 2 && point->observations.size() < min_observations)) {
      map_.ErasePoint(p);
    } else if (age < 3) {
      keep.push_back(p);
    }
  }
  recent_points_ = std::move(keep);
}

std::vector<Slam::NewPoint> Slam::FindNewPoints(const std::vector<KeyFrame>& snapshot,
                                                const std::vector<KeyFrameHandle>& neighbours,
                                                std::pair<double, double> depth_range) const {
  std::vector<NewPoint> out;
  const double baseline = geometry_.bf / geometry_.camera.fx;
  TriangulationOptions tri;
  tri.max_reprojection_error_px = 2.0;
  tri.min_parallax_deg = 0.0;
  const double max_ray_cos = std::cos(options_.min_parallax_deg * M_PI / 180.0);
  const KeyFrame& a = snapshot[0];
  for (size_t k = 0; k < neighbours.size(); ++k) {
    const KeyFrame& b = snapshot[k + 1];
    // Monocular pairs need parallax, which the triangulation test below checks per point.
    if ((a.camera_center() - b.camera_center()).norm() < baseline) continue;
    const Eigen::Matrix3d F = FundamentalBetween(a, b, geometry_.camera);
    for (const auto& [i1, i2] : MatchForTriangulation(a, b, F, depth_range, geometry_, options_.matcher)) {
      const TriangulatedPoint t = TriangulatePoint(geometry_.camera, a.T_cam_world, b.T_cam_world,
                                                   a.uv[i1].cast<double>(), b.uv[i2].cast<double>(), tri);
      Eigen::Vector3d X;
      // Rays that diverge by min_parallax_deg are triangulated; otherwise the stereo or RGB-D
      // depth of the keyframe that sees the point nearer (the wider stereo angle) places it, at
      // any depth: far points, whose rays barely diverge between keyframes on fast forward
      // motion, enter the map from their disparity.
      const double ray_cos = std::cos(t.parallax_deg * M_PI / 180.0);
      const bool depth_a = a.depth[i1] > 0, depth_b = b.depth[i2] > 0;
      if (t.ok() && ray_cos < max_ray_cos) {
        X = t.X_world;
      } else if (depth_a && (!depth_b || a.depth[i1] <= b.depth[i2])) {
        X = Unproject(geometry_.camera, a.T_cam_world, a.uv[i1], a.depth[i1]);
      } else if (depth_b) {
        X = Unproject(geometry_.camera, b.T_cam_world, b.uv[i2], b.depth[i2]);
      } else {
        continue;
      }
      // Every measurement must agree: both projections, and the right image where there is one.
      auto agrees = [&](const KeyFrame& kf, uint32_t i) {
        const Eigen::Vector3d Xc = kf.T_cam_world * X;
        if (Xc.z() <= 0) return false;
        const double u = geometry_.camera.fx * Xc.x() / Xc.z() + geometry_.camera.cx;
        const double v = geometry_.camera.fy * Xc.y() / Xc.z() + geometry_.camera.cy;
        const double eu = u - kf.uv[i].x(), ev = v - kf.uv[i].y();
        double e2 = eu * eu + ev * ev, gate = 5.991;
        if (kf.right_u[i] >= 0) {
          const double er = u - geometry_.bf / Xc.z() - kf.right_u[i];
          e2 += er * er;
          gate = 7.8;
        }
        return e2 * geometry_.pyramid.inv_sigma2[kf.octave[i]] < gate;
      };
      if (!agrees(a, i1) || !agrees(b, i2)) continue;
      out.push_back({neighbours[k], i1, i2, X});
    }
  }
  return out;
}

std::pair<double, double> Slam::SceneDepthRange(KeyFrameHandle h) const {
  const KeyFrame& kf = map_.keyframe(h);
  std::vector<double> depths;
  for (PointHandle p : kf.points)
    if (const MapPoint* point = map_.points().try_get(p)) depths.push_back((kf.T_cam_world * point->position).z());
  if (depths.size() < 10) return {0.05, 1e4};
  std::sort(depths.begin(), depths.end());
  // Well beyond the depths seen so far, both ways: new points lie in the same scene.
  const double near = depths[depths.size() / 20], far = depths[depths.size() - 1 - depths.size() / 20];
  return {std::max(0.01, 0.25 * near), 4.0 * far};
}

void Slam::AddNewPoints(KeyFrameHandle current, const std::vector<NewPoint>& candidates) {
  for (const NewPoint& c : candidates) {
    // The map moved on while matching ran: skip anything erased or bound since.
    const KeyFrame* b = map_.keyframes().try_get(c.neighbour);
    if (!b || !b->points[c.i2].is_null() || !map_.keyframe(current).points[c.i1].is_null()) continue;
    const PointHandle p = map_.AddPoint(c.X_world, current);
    map_.AddObservation(p, current, c.i1);
    map_.AddObservation(p, c.neighbour, c.i2);
    map_.UpdatePointStats(p, map_scales_);
    recent_points_.push_back(p);
  }
}

void Slam::Fuse(KeyFrameHandle current) {
  std::vector<KeyFrameHandle> targets = map_.BestCovisible(current, options_.local_keyframes);
  std::unordered_set<KeyFrameHandle> in_set(targets.begin(), targets.end());
  const size_t first_order = targets.size();
  for (size_t i = 0; i < first_order; ++i)
    for (KeyFrameHandle n : map_.BestCovisible(targets[i], 5))
      if (n != current && in_set.insert(n).second) targets.push_back(n);
  // The current keyframe's points into the neighbours, then the neighbours' points into it.
  std::vector<PointHandle> own;
  for (PointHandle p : map_.keyframe(current).points)
    if (!p.is_null()) own.push_back(p);
  for (KeyFrameHandle t : targets) FusePoints(map_, t, own, geometry_, options_.matcher);
  std::vector<PointHandle> theirs;
  std::unordered_set<PointHandle> unique;
  for (KeyFrameHandle t : targets)
    for (PointHandle p : map_.keyframe(t).points)
      if (!p.is_null() && unique.insert(p).second) theirs.push_back(p);
  FusePoints(map_, current, theirs, geometry_, options_.matcher);
  for (PointHandle p : map_.keyframe(current).points)
    if (map_.points().contains(p)) map_.UpdatePointStats(p, map_scales_);
}

void Slam::LocalBundleAdjustment(KeyFrameHandle current) {
  uint64_t epoch = 0;
  MapBundleAdjustment& ba = local_ba_;  // buffers reused from the last keyframe
  {
    std::lock_guard<std::mutex> lock(map_mutex_);
    if (!map_.keyframes().contains(current)) return;
    epoch = map_epoch_;
    // The window: the new keyframe and its strongest covisible ones; every other keyframe that
    // sees their points enters fixed.
    thread_local std::vector<KeyFrameHandle> window;
    window.assign(1, current);
    for (const auto& [n, w] : map_.keyframe(current).covisible) {
      if (window.size() > options_.max_local_ba_keyframes) break;  // covisible: strongest first
      if (map_.keyframes().contains(n)) window.push_back(n);
    }
    BuildMapBundleAdjustment(map_, geometry_, stereo_depth_, window, first_keyframe_, 1, &ba);
  }
  if (ba.problem.observations.empty()) return;
  // Solved on a copy, without the lock: tracking goes on meanwhile. A keyframe waiting behind
  // this one ends the adjustment early: the next keyframe's adjustment covers the same
  // neighbourhood.
  BundleAdjustmentOptions ba_options = options_.bundle_adjustment;
  ba_options.stop_early = [this] { return pending_keyframes_ > 1 || keyframe_wanted_; };
  const BundleAdjustmentResult result = flatslam::LocalBundleAdjustment(ba.problem, ba_options, &local_ba_workspace_);
  if (result.stopped_early) ++mapping_times_.local_ba_stopped_early;
  if (!result.success) return;

  std::lock_guard<std::mutex> lock(map_mutex_);
  if (epoch != map_epoch_) return;  // the map moved meanwhile: this solution is in its old frame
  ApplyMapBundleAdjustment(ba, result, /*erase_outliers=*/true, &map_);
  for (PointHandle p : ba.points)
    if (map_.points().contains(p)) map_.UpdatePointStats(p, map_scales_);
}

void Slam::CullKeyFrames(KeyFrameHandle current) {
  for (const auto& [h, w] : std::vector<std::pair<KeyFrameHandle, int>>(map_.keyframe(current).covisible)) {
    if (h == first_keyframe_ || h == reference_keyframe_ || !map_.keyframes().contains(h)) continue;
    const KeyFrame& kf = map_.keyframe(h);
    if (!kf.loop_edges.empty()) continue;  // loop closures keep both ends
    int considered = 0, redundant = 0;
    const double close = CloseDepth();
    for (uint32_t i = 0; i < kf.size(); ++i) {
      const MapPoint* point = map_.points().try_get(kf.points[i]);
      if (!point) continue;
      // With depth, only reliable close points count.
      if (!monocular() && (kf.depth[i] <= 0 || kf.depth[i] > close)) continue;
      ++considered;
      if (point->observations.size() <= 3) continue;
      int others = 0;
      for (const Observation& o : point->observations) {
        if (o.keyframe == h) continue;
        const KeyFrame* other = map_.keyframes().try_get(o.keyframe);
        if (other && other->octave[o.keypoint] <= kf.octave[i] + 1) ++others;
        if (others >= 3) break;
      }
      if (others >= 3) ++redundant;
    }
    if (considered > 0 && redundant > options_.redundant_keyframe_ratio * considered) {
      // Frames referring to the culled keyframe keep their absolute pose (see FrameTrajectory).
      EraseKeyFrame(h);
    }
  }
}

Trajectory Slam::FrameTrajectory() const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  Trajectory out;
  out.reserve(frame_poses_.size());
  for (size_t i = 0; i < frame_poses_.size(); ++i) {
    const FramePose& f = frame_poses_[i];
    TimedPose p;
    p.t_ns = f.t_ns;
    p.T_world_cam = ResolveFramePose(f).inverse();
    out.push_back(p);
  }
  return out;
}

Trajectory Slam::KeyFrameTrajectory() const {
  std::lock_guard<std::mutex> lock(map_mutex_);
  std::vector<const KeyFrame*> kfs;
  for (const KeyFrame& kf : map_.keyframes().values()) kfs.push_back(&kf);
  std::sort(kfs.begin(), kfs.end(), [](const KeyFrame* a, const KeyFrame* b) { return a->t_ns < b->t_ns; });
  Trajectory out;
  for (const KeyFrame* kf : kfs) out.push_back({kf->t_ns, kf->T_cam_world.inverse()});
  return out;
}

}  // namespace flatslam
