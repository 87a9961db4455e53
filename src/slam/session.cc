#include "slam/session.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>

#include <tbb/parallel_invoke.h>

#include "core/clock.h"
#include "core/error.h"
#include "frontend/stereo_matcher.h"
#include "io/orb_settings.h"
#include "place/vocabulary.h"

namespace flatslam {
// The access each step takes. Local mapping's buffers (the keyframe copies, the BA problem and
// workspace) belong to the one mapping node and are not a shared component: triangulation and
// the local BA solve take no access at all, and tracking runs beside them.
namespace SessionAccess {
using C = Component;
constexpr Access kTrack = Access::Of({C::kPlaceIndex}, {C::kMap, C::kTracker, C::kLocalMapping, C::kTrajectory});
constexpr Access kForceLost = Access::Of({}, {C::kTracker});
constexpr Access kPrepare = Access::Of({}, {C::kMap, C::kLocalMapping});
constexpr Access kAddPoints = Access::Of({}, {C::kMap, C::kLocalMapping});
constexpr Access kBuildLocalBa = Access::Of({C::kMap, C::kTracker}, {});
constexpr Access kApplyLocalBa = Access::Of({}, {C::kMap});
constexpr Access kCull = Access::Of({C::kTracker}, {C::kMap, C::kLocalMapping, C::kPlaceIndex});
constexpr Access kPlace = Access::Of({}, {C::kMap, C::kPlaceIndex, C::kLoops});
constexpr Access kBuildGlobalBa = Access::Of({C::kMap, C::kTracker}, {});
constexpr Access kApplyGlobalBa = Access::Of({C::kLoops}, {C::kMap});
constexpr Access kAdoptMap =
    Access::Of({}, {C::kMap, C::kTracker, C::kLocalMapping, C::kPlaceIndex, C::kLoops, C::kTrajectory});
constexpr Access kCapture = Access::Of({C::kMap, C::kLocalMapping, C::kTrajectory}, {});
constexpr Access kFrameTrajectory = Access::Of({C::kMap, C::kLocalMapping, C::kTrajectory}, {});
constexpr Access kKeyFrameTrajectory = Access::Of({C::kMap}, {});
constexpr Access kReadMap = Access::Of({C::kMap}, {});
constexpr Access kMoveFrame = Access::Of({}, {C::kMap, C::kTracker, C::kLocalMapping, C::kTrajectory});
constexpr Access kAfterLastFrame = Access::Of({C::kLoops}, {C::kMap});
}  // namespace SessionAccess

std::span<const AccessStep> SlamSession::Steps() {
  using namespace SessionAccess;
  static constexpr AccessStep kSteps[] = {
      {"extract", Access{}, "extract", /*parallel=*/true, /*guarded=*/false},
      {"track", kTrack, "track", false, true},
      {"force_lost", kForceLost, "track", false, true},
      {"mapping.prepare", kPrepare, "mapping", false, true},
      {"mapping.triangulate", Access{}, "mapping", false, false},
      {"mapping.add_points", kAddPoints, "mapping", false, true},
      {"mapping.build_local_ba", kBuildLocalBa, "mapping", false, true},
      {"mapping.solve_local_ba", Access{}, "mapping", false, false},
      {"mapping.apply_local_ba", kApplyLocalBa, "mapping", false, true},
      {"mapping.cull", kCull, "mapping", false, true},
      {"place", kPlace, "mapping", false, true},
      {"mapping.publish", kReadMap, "mapping", false, true},
      {"mapping.move_frame", kMoveFrame, "mapping", false, true},
      {"mapping.after_last_frame", kAfterLastFrame, "mapping", false, true},
      {"global_ba.build", kBuildGlobalBa, "background", false, true},
      {"global_ba.solve", Access{}, "background", false, false},
      {"global_ba.apply", kApplyGlobalBa, "background", false, true},
      {"checkpoint.capture", kCapture, "checkpoint", false, true},
  };
  return kSteps;
}

SlamSession::SlamSession(const Calibration& calibration, const SlamOptions& options)
    : SlamSession(calibration, ResolvedOptions(options, calibration)) {}

SlamSession::SlamSession(const Calibration& calibration, SlamOptions&& resolved)
    : extractor_(resolved.orb),
      context_(calibration, resolved, extractor_.scales()),
      tracker_(resolved.seed),
      database_(resolved.vocabulary ? resolved.vocabulary->word_count() : 0),
      loops_(resolved.seed + 1) {
  if (context_.options.localization_only) tracker_.allow_new_segments = false;
  frame_poses_.SpillToFile();  // a session of any length keeps two chunks of frame records in memory
}

namespace {

// Moves keypoints measured in the given camera's image into `camera` through `lens` and drops
// those that land outside its image, as an undistorted image would have no pixel there.
void UndistortKeypoints(const RefinedCamera& lens, const PinholeCamera& camera, Keypoints* keypoints) {
  std::vector<Eigen::Vector2d> given(keypoints->size());
  for (size_t i = 0; i < given.size(); ++i) given[i] = keypoints->uv[i].cast<double>();
  const std::vector<Eigen::Vector2d> moved = lens.FromGiven(given);
  std::vector<uint8_t> keep(moved.size());
  for (size_t i = 0; i < moved.size(); ++i) {
    const Eigen::Vector2d& p = moved[i];
    keep[i] = p.x() >= 0 && p.y() >= 0 && p.x() <= camera.width - 1 && p.y() <= camera.height - 1;
    keypoints->uv[i] = p.cast<float>();
  }
  keypoints->Keep(keep);
}

}  // namespace

void SlamSession::Extract(const Frame& frame, TrackedFrame* out, Keypoints* measured) const {
  const Calibration& calibration = context_.calibration;
  const PinholeCamera& cam = calibration.camera;
  FLATSLAM_CHECK(frame.left.cols == cam.width && frame.left.rows == cam.height, "frame ", frame.index, " is ",
                 frame.left.cols, "x", frame.left.rows, ", calibration says ", cam.width, "x", cam.height);
  FLATSLAM_CHECK(!frame.lens || calibration.sensor == Sensor::kMonocular, "frame ", frame.index,
                 ": only monocular images are undistorted keypoint by keypoint");
  FLATSLAM_CHECK(!measured || calibration.sensor == Sensor::kMonocular, "frame ", frame.index,
                 ": only a monocular frame is made again from its measured keypoints");
  out->index = frame.index;
  out->t_ns = frame.t_ns;
  // Pooled pyramids: their levels are not reallocated per frame.
  const auto left_pyramid = pyramids_.Acquire();
  if (calibration.sensor == Sensor::kStereo) {
    FLATSLAM_CHECK(!frame.right.empty(), "frame ", frame.index, " has no right image");
    Keypoints right;
    const auto right_pyramid = pyramids_.Acquire();
    tbb::parallel_invoke([&] { extractor_.Extract(frame.left, &out->keypoints, left_pyramid.get()); },
                         [&] { extractor_.Extract(frame.right, &right, right_pyramid.get()); });
    MatchStereo(right, *left_pyramid, *right_pyramid, extractor_.scales(), cam.fx, calibration.baseline_m,
                context_.options.stereo, &out->keypoints);
    right_pyramid->levels[0].release();  // level 0 shares the input image: do not keep it alive
  } else {
    FLATSLAM_CHECK(calibration.sensor == Sensor::kMonocular || !frame.depth.empty(), "frame ", frame.index,
                   " has no depth image");
    extractor_.Extract(frame.left, &out->keypoints, left_pyramid.get());
    if (measured) *measured = out->keypoints;
    if (frame.lens) UndistortKeypoints(*frame.lens, cam, &out->keypoints);
    if (calibration.sensor == Sensor::kRgbd)
      DepthFromImage(frame.depth, cam.fx, context_.options.rgbd_virtual_baseline_m, &out->keypoints);
  }
  left_pyramid->levels[0].release();
  out->Prepare(cam.width, cam.height);
}

void SlamSession::ExtractFrom(const Keypoints& measured, const Frame& frame, TrackedFrame* out) const {
  const Calibration& calibration = context_.calibration;
  FLATSLAM_CHECK(calibration.sensor == Sensor::kMonocular, "frame ", frame.index,
                 ": only a monocular frame is made again from its measured keypoints");
  out->index = frame.index;
  out->t_ns = frame.t_ns;
  out->keypoints = measured;
  if (frame.lens) UndistortKeypoints(*frame.lens, calibration.camera, &out->keypoints);
  out->Prepare(calibration.camera.width, calibration.camera.height);
}

FrameReport SlamSession::Track(TrackedFrame&& frame, std::optional<KeyFrameHandle>* new_keyframe) {
  const auto start = std::chrono::steady_clock::now();
  new_keyframe->reset();
  const auto lease = access_.Acquire(SessionAccess::kTrack);
  FLATSLAM_CHECK(!frames_over_, "frame ", frame.index, ": the session's map was edited after its last frame");
  next_frame_ = frame.index + 1;
  if (tracker_.state != TrackingState::kNotInitialized && map_corrected_ && tracker_.last_frame &&
      !frame_poses_.empty()) {
    // A loop correction or global BA moved the map: the last frame follows its reference keyframe.
    tracker_.last_frame->T_cam_world =
        ResolveFramePose(map_, mapping_.culled, frame_poses_.back(), MovesSince(frame_moves_, frame_poses_.size() - 1));
    map_corrected_ = false;
  }
  // Tracking reads the map; the mapping system then writes what it found.
  TrackResult result = TrackFrame(map_, database_, context_, tracker_, frame, pending_keyframes_);
  if (result.keyframe_wanted) keyframe_wanted_ = *result.keyframe_wanted;
  const InsertedTwoView inserted = ApplyTrackResult(frame, result);
  if (const std::optional<AnchoredFramePose> pose =
          FinishFrame(map_, tracker_, std::move(frame), result, inserted, new_keyframe))
    frame_poses_.push_back(*pose);
  FrameReport& report = result.report;
  report.keyframe = new_keyframe->has_value();
  report.map_keyframes = map_.keyframes().size();
  report.map_points = map_.points().size();
  report.map_frame = map_frame_moves_;
  if (report.keyframe) ++pending_keyframes_;
  report.track_ms = MsSince(start);
  return report;
}

InsertedTwoView SlamSession::ApplyTrackResult(TrackedFrame& frame, TrackResult& result) {
  ApplySightings(map_, result.visible, result.found);
  InsertedTwoView inserted;
  switch (result.insert) {
    case TrackResult::Insert::kNone:
      break;
    case TrackResult::Insert::kKeyFrame:
    case TrackResult::Insert::kFirstKeyFrame:
      inserted.first = InsertKeyFrame(map_, mapping_, context_, frame,
                                      /*all_depth_points=*/result.insert == TrackResult::Insert::kFirstKeyFrame);
      break;
    case TrackResult::Insert::kTwoView:
      inserted = InsertTwoViewMap(map_, mapping_, context_, *result.two_view, frame);
      break;
  }
  return inserted;
}

void SlamSession::MapKeyFrame(KeyFrameHandle keyframe) {
  std::pair<double, double> depth_range;
  uint64_t epoch = 0;
  size_t frame_index = 0;
  struct Done {
    std::atomic<int>& pending;
    ~Done() { --pending; }
  } done{pending_keyframes_};
  MappingTimes& times = mapping_.times;
  auto stage_start = std::chrono::steady_clock::now();
  auto lap = [&stage_start](double* total) {
    const auto now = std::chrono::steady_clock::now();
    *total += Milliseconds(now - stage_start);
    stage_start = now;
  };
  {
    const auto lease = access_.Acquire(SessionAccess::kPrepare);
    if (!PrepareKeyFrame(map_, mapping_, context_, keyframe, &depth_range)) return;
    frame_index = map_.keyframe(keyframe).frame_index;
    epoch = map_epoch_;
  }
  ++times.keyframes;
  lap(&times.prepare_ms);
  // The words come first: monocular triangulation searches keypoints under the same node.
  KeyFrame& copy = mapping_.snapshot[0];
  if (context_.options.vocabulary)
    context_.options.vocabulary->Transform(copy.descriptor, &copy.bow, &copy.bow_features);
  const std::vector<NewPoint> candidates = FindNewPoints(mapping_, context_, depth_range);
  BowVector bow = std::move(copy.bow);
  FeatureVector bow_features = std::move(copy.bow_features);
  lap(&times.triangulate_ms);
  {
    const auto lease = access_.Acquire(SessionAccess::kAddPoints);
    if (!map_.keyframes().contains(keyframe)) return;
    map_.keyframe(keyframe).bow = std::move(bow);
    map_.keyframe(keyframe).bow_features = std::move(bow_features);
    // Points triangulated before the map moved are in its old frame: dropped.
    AddNewPointsAndFuse(map_, mapping_, context_, keyframe, candidates, /*add_points=*/epoch == map_epoch_);
  }
  lap(&times.fuse_ms);
  {
    // Solved on a copy, without the lock: tracking goes on meanwhile. A keyframe waiting behind
    // this one ends the adjustment early: the next keyframe's adjustment covers the same
    // neighbourhood.
    bool built = false;
    {
      const auto lease = access_.Acquire(SessionAccess::kBuildLocalBa);
      epoch = map_epoch_;
      built = BuildLocalBundleAdjustment(map_, mapping_, context_, keyframe, tracker_.first_keyframe);
    }
    if (built) {
      const BundleAdjustmentResult result =
          SolveLocalBundleAdjustment(mapping_, context_, [this] { return pending_keyframes_ > 1 || keyframe_wanted_; });
      const auto lease = access_.Acquire(SessionAccess::kApplyLocalBa);
      // The map moved meanwhile: this solution is in its old frame.
      if (result.success && epoch == map_epoch_) ApplyLocalBundleAdjustment(map_, mapping_, context_, result);
    }
  }
  lap(&times.local_ba_ms);
  {
    const auto lease = access_.Acquire(SessionAccess::kCull);
    const KeyFrameHandle keep[] = {tracker_.first_keyframe, tracker_.reference_keyframe};
    CullKeyFrames(map_, mapping_, context_, keyframe, keep,
                  [this](KeyFrameHandle h, const KeyFrame& kf) { database_.Erase(h, kf.bow); });
  }
  lap(&times.cull_ms);
  // A failed loop correction costs that loop, not the session: it becomes a warning and the next
  // keyframes are searched as usual.
  try {
    DetectAndCloseLoop(keyframe);
  } catch (const std::exception& e) {
    loops_.consistent_groups.clear();
    Warn("loop closing failed at the keyframe of frame " + std::to_string(frame_index) +
         ", the session goes on without this loop: " + e.what());
  }
  lap(&times.place_ms);
}

void SlamSession::DetectAndCloseLoop(KeyFrameHandle current) {
  if (!context_.options.vocabulary) return;
  size_t loops = 0;
  {
    const auto lease = access_.Acquire(SessionAccess::kPlace);
    const std::optional<LoopMatch> match =
        DetectLoop(map_, database_, loops_, context_, current, context_.options.loop_closing && !global_ba_running_);
    if (!match) return;
    if (context_.options.inject_fault == InjectedFault::kLoopClosing) Fail("injected failure in loop correction");
    CorrectLoop(map_, loops_, context_, current, *match);
    map_corrected_ = true;
    ++map_epoch_;
    ++map_corrections_;
    if (!context_.options.global_bundle_adjustment || abandon_background_) return;
    global_ba_running_ = true;
    loops = loops_.closures.size();
  }
  // Started after the place step released its access: the adjustment takes its own (inline,
  // on this thread, when no background lane is set).
  LaunchGlobalBundleAdjustment(loops);
}

void SlamSession::StartGlobalBundleAdjustment() {
  if (!context_.options.global_bundle_adjustment || abandon_background_ || map_.keyframes().empty()) return;
  global_ba_running_ = true;
  LaunchGlobalBundleAdjustment(loops_.closures.size());
}

void SlamSession::LaunchGlobalBundleAdjustment(size_t loops) {
  auto task = [this, loops] {
    try {
      GlobalBundleAdjustment(loops);
    } catch (const std::exception& e) {
      global_ba_running_ = false;
      // A failure here costs the refinement, not the session: it becomes a warning.
      Warn(std::string("global bundle adjustment failed, the map keeps its loop correction: ") + e.what());
    }
  };
  if (background_)
    background_(std::move(task));
  else
    task();
}

void SlamSession::GlobalBundleAdjustment(size_t loops) {
  struct Clear {
    std::atomic<bool>& flag;
    ~Clear() { flag = false; }
  } clear{global_ba_running_};
  if (context_.options.inject_fault == InjectedFault::kGlobalBundleAdjustment)
    Fail("injected failure in global bundle adjustment");
  MapBundleAdjustment ba;
  uint64_t epoch = 0;
  {
    const auto lease = access_.Acquire(SessionAccess::kBuildGlobalBa);
    if (!BuildGlobalBundleAdjustment(map_, context_, tracker_.first_keyframe, &ba)) return;
    epoch = map_epoch_;
  }
  const BundleAdjustmentResult result =
      SolveGlobalBundleAdjustment(ba, context_, [this] { return abandon_background_.load(); });
  if (!result.success || abandon_background_) return;
  const auto lease = access_.Acquire(SessionAccess::kApplyGlobalBa);
  // A newer loop, or a move of the map's frame, moved the map: this solution is stale.
  if (loops_.closures.size() != loops || epoch != map_epoch_) return;
  ApplyGlobalBundleAdjustment(map_, context_, ba, result);
  map_corrected_ = true;
  ++map_epoch_;
  ++map_corrections_;
}

void SlamSession::MoveMapFrame(const Eigen::Isometry3d& T_new_old, double scale) {
  FLATSLAM_CHECK(std::isfinite(scale) && scale > 0, "moving the map's frame: scale ", scale, " is not positive");
  FLATSLAM_CHECK(scale == 1.0 || context_.monocular(), "moving the map's frame: scale ", scale,
                 " for a stereo or RGB-D map, whose depths are metric (only a monocular map may scale)");
  const auto lease = access_.Acquire(SessionAccess::kMoveFrame);
  map_.MoveFrame(T_new_old, scale);
  if (tracker_.velocity) tracker_.velocity->translation() *= scale;
  if (tracker_.init_frame)
    tracker_.init_frame->T_cam_world = MovedCameraPose(tracker_.init_frame->T_cam_world, T_new_old, scale);
  for (auto& [handle, culled] : mapping_.culled) culled.T_kf_parent.translation() *= scale;
  frame_moves_.push_back({frame_poses_.size(), Similarity3{T_new_old.linear(), T_new_old.translation(), scale}});
  map_corrected_ = true;
  ++map_epoch_;
  ++map_frame_moves_;
}

void SlamSession::EditMapAfterLastFrame(const std::function<void(Map&)>& edit) {
  const auto lease = access_.Acquire(SessionAccess::kAfterLastFrame);
  FLATSLAM_CHECK(pending_keyframes_.load() == 0 && !global_ba_running_.load(),
                 "the map can be edited after the last frame only once mapping and global adjustment are done");
  frames_over_ = true;
  edit(map_);
  map_corrected_ = true;
  ++map_epoch_;
}

void SlamSession::ForceLost() {
  const auto lease = access_.Acquire(SessionAccess::kForceLost);
  tracker_.force_lost = true;
}

void SlamSession::AdoptMap(Map&& map, std::span<const AnchoredFramePose> frames, bool resume_tracking) {
  FLATSLAM_CHECK(context_.options.vocabulary, "continuing a saved map needs a vocabulary to relocalize in it");
  const auto lease = access_.Acquire(SessionAccess::kAdoptMap);
  FLATSLAM_CHECK(tracker_.state == TrackingState::kNotInitialized && map_.keyframes().empty(),
                 "a map can only be adopted before the first frame");
  FLATSLAM_CHECK(!map.keyframes().empty(), "the map to continue has no keyframes");
  map_ = std::move(map);
  const auto handles = map_.keyframes().handles();
  const std::vector<KeyFrameHandle> kfs(handles.begin(), handles.end());
  KeyFrameHandle& first = tracker_.first_keyframe;
  for (KeyFrameHandle h : kfs) {
    KeyFrame& kf = map_.keyframe(h);
    context_.options.vocabulary->Transform(kf.descriptor, &kf.bow, &kf.bow_features);
    database_.Add(h, kf.bow);
    // A spanning-tree root anchors the map's frame (bundle adjustment holds it fixed).
    if (first.is_null() || (kf.parent.is_null() && !map_.keyframe(first).parent.is_null())) first = h;
  }
  for (AnchoredFramePose pose : frames) {
    if (!map_.keyframes().contains(pose.reference)) pose.reference = KeyFrameHandle::null();
    frame_poses_.push_back(pose);
  }
  // Points the continued session still had on probation (made by its last three keyframes) stay
  // on probation here, so that recent-point culling drops the bad ones as it would have.
  uint64_t newest = 0;
  for (const KeyFrame& kf : map_.keyframes().values()) {
    newest = std::max(newest, kf.id);
    tracker_.last_keyframe_frame = std::max(tracker_.last_keyframe_frame, kf.frame_index);
  }
  for (PointHandle p : map_.points().handles())
    if (map_.point(p).first_keyframe_id + 3 > newest) mapping_.recent_points.push_back(p);
  tracker_.segment_keyframes = map_.keyframes().size();
  tracker_.state = TrackingState::kLost;
  tracker_.allow_new_segments = false;
  if (resume_tracking && frame_poses_.size() >= 2)
    ResumeTracking(map_, context_, frame_poses_[frame_poses_.size() - 2], frame_poses_.back(), tracker_);
}

void SlamSession::CaptureState(State* out) const {
  const auto lease = access_.Acquire(SessionAccess::kCapture);
  out->map.AssignForSnapshot(map_);
  frame_poses_.TakeView(&out->frames);
  out->culled = mapping_.culled;
  out->moves = frame_moves_;
  out->next_frame = next_frame_;
  out->global_adjustment_pending = global_ba_running_.load();
}

void SlamSession::ReadMap(const std::function<void(const Map&)>& read) const {
  const auto lease = access_.Acquire(SessionAccess::kReadMap);
  read(map_);
}

void SlamSession::State::AnchoredToMap(std::vector<AnchoredFramePose>* out) const {
  out->clear();
  out->reserve(frames.size());
  size_t i = 0;
  frames.ForEach([&](AnchoredFramePose a) {
    const Similarity3 since = MovesSince(moves, i++);
    Eigen::Isometry3d T_cam_ref = a.T_cam_ref.isometry();
    T_cam_ref.translation() *= since.s;
    if (FollowToLiveKeyFrame(map, culled, &a.reference, &T_cam_ref))
      a.T_cam_ref = CompactPose(T_cam_ref);
    else
      a.reference = KeyFrameHandle::null();
    if (!moves.empty()) a.T_cam_world = CompactPose(MovedCameraPose(a.T_cam_world.isometry(), since));
    out->push_back(a);
  });
}

void SlamSession::Warn(const std::string& message) const {
  if (warning_sink_)
    warning_sink_(message);
  else
    std::fprintf(stderr, "warning: %s\n", message.c_str());
}

Trajectory SlamSession::FrameTrajectory() const {
  const auto lease = access_.Acquire(SessionAccess::kFrameTrajectory);
  Trajectory out;
  out.reserve(frame_poses_.size());
  size_t i = 0;
  frame_poses_.ForEach([&](const AnchoredFramePose& f) {
    out.push_back({f.t_ns, ResolveFramePose(map_, mapping_.culled, f, MovesSince(frame_moves_, i++)).inverse()});
  });
  return out;
}

Similarity3 SlamSession::MovesSince(std::span<const FrameMoveRecord> moves, size_t i) {
  Similarity3 since;
  for (const FrameMoveRecord& m : moves)
    if (m.frames_before > i) since = m.move * since;  // the later move after the earlier ones
  return since;
}

Trajectory SlamSession::KeyFrameTrajectory() const {
  const auto lease = access_.Acquire(SessionAccess::kKeyFrameTrajectory);
  std::vector<const KeyFrame*> kfs;
  for (const KeyFrame& kf : map_.keyframes().values()) kfs.push_back(&kf);
  std::sort(kfs.begin(), kfs.end(), [](const KeyFrame* a, const KeyFrame* b) { return a->t_ns < b->t_ns; });
  Trajectory out;
  for (const KeyFrame* kf : kfs) out.push_back({kf->t_ns, kf->T_cam_world.inverse()});
  return out;
}

}  // namespace flatslam
