// The SLAM core for monocular, stereo and RGB-D input: feature extraction (parallel across frames),
// tracking (serial, in frame order) and local mapping (a background job per keyframe).
// Concurrency: Extract() is const and runs on many frames at once; Track() is called from one
// serial stage; MapKeyFrame() from one background queue. Track and MapKeyFrame share the map
// through one map mutex held for short critical sections; local bundle adjustment solves a
// copy of its window without the lock and writes back through handles, skipping any entity
// erased meanwhile.
#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <mutex>
#include <optional>
#include <random>
#include <span>
#include <string>
#include <unordered_map>
#include <vector>

#include "core/object_pool.h"
#include "ecs/chunk_log.h"
#include "ecs/map.h"
#include "io/types.h"
#include "optimization/bundle_adjustment.h"
#include "frontend/frame.h"
#include "place/keyframe_database.h"
#include "mapping/map_bundle_adjustment.h"
#include "matching/matcher.h"
#include "frontend/orb_extractor.h"
#include "optimization/pose_optimizer.h"
#include "frontend/stereo_matcher.h"

namespace flatslam {

class Vocabulary;

// Test hook: background work that throws on purpose, to check that failures surface as warnings
// and the session goes on. Never set by a user option.
enum class InjectedFault : uint8_t { kNone, kGlobalBundleAdjustment, kLoopClosing };

// The ORB options SLAM starts from: the extractor's, with the feature budget left to the camera.
[[nodiscard]] inline OrbOptions SlamOrbDefaults() {
  OrbOptions orb;
  orb.features = 0;
  return orb;
}

struct SlamOptions {
  // Extraction; orb.features 0 = derived from the camera (see ResolvedOptions).
  OrbOptions orb = SlamOrbDefaults();
  StereoOptions stereo;
  MatcherOptions matcher;
  PoseOptimizerOptions pose;
  BundleAdjustmentOptions bundle_adjustment;
  double rgbd_virtual_baseline_m = 0.08;  // RGB-D depth becomes a stereo measurement with this baseline
  // "Close" points (reliable stereo depth) are nearer than this x baseline: created from one frame,
  // counted for keyframe decisions and culling. ORB-SLAM2 uses 35 for KITTI and EuRoC, 40 for TUM.
  double close_depth_baselines = 35;
  // Stereo keypoints deeper than this x baseline count as monocular observations in pose
  // optimization and bundle adjustment (0: never): their disparity is a few pixels, where a tenth
  // of a pixel of rectification error is a percent of depth, and it biased the trajectory's scale
  // (KITTI 06: 0.4% too long with them). They still give rotation, and depth once triangulated
  // over keyframes. 35 is ORB-SLAM2's close-depth threshold for KITTI and EuRoC. A frame whose
  // median measured depth lies beyond it keeps stereo up to that median (the scale needs them).
  double far_stereo_baselines = kFarStereoBaselines;
  int min_init_points = 150;             // keypoints with depth needed to start a map (stereo/RGB-D)
  int min_init_matches = 100;            // monocular: matches between the two initial frames
  float mono_search_radius = 15;         // monocular: projection search radius, pixels x level scale
  uint64_t seed = 1;                     // RANSAC of the monocular initialization
  int min_motion_inliers = 10;           // after frame-to-frame tracking
  int min_local_map_inliers = 30;        // after tracking the local map
  float motion_search_radius = 7;        // pixels (x level scale) around the predicted position
  int max_frames_between_keyframes = 0;  // 0 = the frame rate (one second)
  // An idle local mapping takes a keyframe only this many frames after the last; -1 = by sensor
  // (2 monocular: forward motion thins the tracked points every frame; 0 with depth).
  int min_frames_between_keyframes = -1;
  size_t local_keyframes = 10;  // covisible keyframes used for triangulation
  // Least angle between the rays of a point triangulated from two keyframes; 0 = by sensor: 2 deg
  // monocular (depth within about 4% at a pixel of noise; on KITTI 07 it also keeps out cars
  // driving ahead, whose features look like points at infinity), 1.146 deg (ORB-SLAM2's cos 0.9998)
  // with depth, where close points come from the stereo or depth measurement.
  double min_parallax_deg = 0;
  size_t max_local_map_keyframes = 80;  // keyframes whose points are tracked
  // Free keyframes of local BA: the new one and its strongest covisible. Bounds a keyframe's cost where
  // far points make every recent keyframe covisible (fast forward motion); the rest of their
  // observers still enter as fixed poses.
  size_t max_local_ba_keyframes = 20;
  double redundant_keyframe_ratio = 0.9;  // culled when this share of its points is seen by 3 others
  // Revisits: when an older keyframe (not one of the last 20 made) already views the scene from
  // within this fraction of the median scene depth, with its optical axis within 20 degrees, a
  // keyframe is made only if tracking is weak (under half the reference keyframe's points, or
  // under 50 close points). Keeps the map from growing while a place is revisited; 0 = off.
  double revisit_radius = 0.1;
  uint32_t agent = 0;              // stamped on every keyframe (multi-agent maps)
  bool localization_only = false;  // track against the map without changing it (no keyframes)
  // Place recognition. Without a vocabulary there is no relocalization and no loop closing.
  const Vocabulary* vocabulary = nullptr;  // must outlive the Slam
  bool loop_closing = true;
  bool global_bundle_adjustment = true;  // after each loop correction, in the background
  int relocalization_frames = 10;        // lost frames spent relocalizing before a new map segment starts
  int loop_consistency = 3;              // consecutive keyframes that must agree on a loop
  int min_loop_matches = 40;             // map points matched across the loop after the Sim(3)/SE(3) search
  InjectedFault inject_fault = InjectedFault::kNone;  // tests only (see InjectedFault)

  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const;
  [[nodiscard]] bool Check() const { return Problem().empty(); }
};

// An option whose value ResolvedOptions chose from the calibration, and the rule it followed.
struct DerivedOption {
  std::string key;   // as in slam_config.h ("orb.features")
  std::string rule;  // one line: the rule and its inputs
};

// The options a Slam for this calibration runs with: values left to the camera or sensor (0 or -1
// above) filled in, the monocular search radius in place of the motion one. Each value filled in
// is listed in *derived (when given) with its rule.
[[nodiscard]] SlamOptions ResolvedOptions(const SlamOptions& options, const Calibration& calibration,
                                          std::vector<DerivedOption>* derived = nullptr);

// Features per image for a camera: one per 300 square pixels, times sqrt(20 Hz / frame rate)
// below 20 Hz, rounded to the 1-1.2-1.5-2-2.5-3-4-5-6-8 series and kept in [500, 8000].
[[nodiscard]] int DerivedFeatureBudget(const PinholeCamera& camera, double frame_rate_hz);

enum class TrackingState { kNotInitialized, kOk, kLost };

// Culled keyframes and where frames that referred to them go instead: the parent, and the culled
// keyframe's pose relative to it.
struct CulledKeyFrame {
  KeyFrameHandle parent;
  Eigen::Isometry3d T_kf_parent;
};
using CulledKeyFrames = std::unordered_map<KeyFrameHandle, CulledKeyFrame>;

// Moves *ref along culled keyframes' parents to a keyframe of `map`, composing *T_cam_ref; false
// when none is left to follow.
bool FollowToLiveKeyFrame(const Map& map, const CulledKeyFrames& culled, KeyFrameHandle* ref,
                          Eigen::Isometry3d* T_cam_ref);

// One loop closure, for the run summary and tests.
struct LoopClosure {
  size_t frame_index = 0;              // input frame of the keyframe that closed the loop
  size_t matched_frame_index = 0;      // input frame of the keyframe it matched
  int64_t t_ns = 0, matched_t_ns = 0;  // their timestamps
  int matches = 0;                     // map points matched across the loop
  double scale = 1;                    // Sim(3) scale of the correction (1 for stereo/RGB-D)
  double correction_m = 0;             // how far the closing keyframe moved
  double correction_ms = 0;            // fusion + essential graph
};
[[nodiscard]] const char* TrackingStateName(TrackingState state);

// Per-frame outcome of Track(), for stats.csv and the run summary.
struct FrameReport {
  size_t index = 0;
  int64_t t_ns = 0;
  TrackingState state = TrackingState::kNotInitialized;
  bool keyframe = false;
  bool reinitialized = false;  // tracking was lost and a new map segment started here
  bool relocalized = false;    // tracking was lost and resumed in the existing map here
  int features = 0;
  int stereo_points = 0;  // keypoints with depth
  int matches = 0;        // map points matched before the final pose optimization
  int inliers = 0;
  size_t map_keyframes = 0;  // keyframes in the map after this frame
  size_t map_points = 0;     // map points after this frame
  double extract_ms = 0;
  double track_ms = 0;
  // The frame's image could not be read; it was never given to tracking (see SlamRunOptions).
  bool skipped = false;
  // The pose tracking gave the frame (T_world_cam), when it joined the trajectory.
  std::optional<Eigen::Isometry3d> T_world_cam;
};

// Where local mapping spends its time, summed over the keyframes it mapped (milliseconds).
struct MappingTimes {
  size_t keyframes = 0;               // keyframes mapped
  double prepare_ms = 0;              // point statistics, covisibility, recent-point culling, copies
  double triangulate_ms = 0;          // bag of words and new points against the neighbours (no lock)
  double fuse_ms = 0;                 // adding the new points, fusing duplicates
  double local_ba_ms = 0;             // local bundle adjustment (solved without the lock)
  double cull_ms = 0;                 // redundant keyframes
  double place_ms = 0;                // keyframe database, loop detection and correction
  size_t local_ba_stopped_early = 0;  // adjustments ended early for a waiting keyframe
};

class Slam {
 public:
  // Throws flatslam::Error on invalid options or calibration.
  Slam(const Calibration& calibration, const SlamOptions& options);

  // Extracts features (left and right in parallel) and stereo/RGB-D depth into *out.
  void Extract(const Frame& frame, TrackedFrame* out) const;
  // Tracks the frame. When it becomes a keyframe, *new_keyframe is set: pass it to MapKeyFrame().
  FrameReport Track(TrackedFrame&& frame, std::optional<KeyFrameHandle>* new_keyframe);
  // Local mapping for one keyframe: point upkeep, triangulation, fusion, local BA, culling.
  void MapKeyFrame(KeyFrameHandle keyframe);

  // Estimated camera poses of all tracked frames (T_world_cam), refined by mapping through
  // their reference keyframes. Call when no stage is running.
  [[nodiscard]] Trajectory FrameTrajectory() const;
  [[nodiscard]] Trajectory KeyFrameTrajectory() const;
  // Direct map access when no stage is running.
  [[nodiscard]] const Map& map() const { return map_; }
  [[nodiscard]] int pending_keyframes() const { return pending_keyframes_; }
  // Tracking wanted a keyframe on the last frame but local mapping was busy; local BA stops early
  // while it is set, and a batch run waits for mapping instead of tracking on.
  [[nodiscard]] bool keyframe_wanted() const { return keyframe_wanted_; }
  // Loop closures so far (call when no stage is running).
  [[nodiscard]] const std::vector<LoopClosure>& loop_closures() const { return loop_closures_; }
  [[nodiscard]] size_t database_size() const { return database_.size(); }
  // Local mapping's time per stage (call when no stage is running).
  [[nodiscard]] const MappingTimes& mapping_times() const { return mapping_times_; }
  // Where background work (global bundle adjustment after a loop) runs: `start` is handed each
  // task and must run it off the calling (mapping) thread, waiting first for the task it was
  // handed before; its owner (src/jobs) waits for the last one before the session ends. Unset:
  // tasks run inline, on the mapping thread. Set before the first frame.
  void SetBackground(std::function<void(std::function<void()>)> start) { background_ = std::move(start); }
  // Ends background work at once (an interrupted session): a running global bundle adjustment
  // stops at its next iteration and its result is dropped; none starts afterwards. The caller
  // then waits for the running task where it runs.
  void AbandonBackground() { abandon_background_ = true; }
  // Receives one line when background work fails and the session goes on without it (global
  // bundle adjustment, loop closing). Called on the failing thread; set before the first frame.
  // Unset: the line goes to stderr.
  void SetWarningSink(std::function<void(const std::string&)> sink) { warning_sink_ = std::move(sink); }
  // Forces tracking lost from the next frame on (tests and the --lose-at option).
  void ForceLost();
  // Continues a saved map (call before the first frame): its keyframes are indexed for place
  // recognition and tracking starts by relocalizing in it. Needs a vocabulary. A session on an
  // adopted map never starts a new map segment: it stays lost until it relocalizes. `frames` is the
  // trajectory of the session being continued (references are keyframes of `map`, or null):
  // FrameTrajectory() starts with them, and later corrections of the map move them too.
  void AdoptMap(Map&& map, std::span<const AnchoredFramePose> frames = {});
  // The session between two frames, for a checkpoint: a copy of the map (Map::AssignForSnapshot:
  // no bags of words), a view of every tracked frame's pose as recorded, the culled keyframes
  // those records may still name, and the frame after the last one tracked. Any thread; holds the
  // map lock while copying (Track and mapping wait meanwhile). Pass the same State each time: the
  // copy then moves little more than what changed since the last. The frame view reads the Slam's
  // own records: use a State only while its Slam lives.
  struct State {
    Map map;
    ChunkLog<AnchoredFramePose>::View frames;
    CulledKeyFrames culled;
    size_t next_frame = 0;  // input index after the last frame given to Track
    // Every frame anchored at a keyframe of `map` (culled references followed to live ones; none
    // where no live keyframe is left), for a snapshot's session.
    void AnchoredToMap(std::vector<AnchoredFramePose>* out) const;
  };
  void CaptureState(State* out) const;

 private:
  using FramePose = AnchoredFramePose;
  static_assert(sizeof(FramePose) == 72);

  bool Initialize(TrackedFrame& frame);
  bool InitializeMonocular(TrackedFrame& frame);
  [[nodiscard]] bool monocular() const { return calibration_.sensor == Sensor::kMonocular; }
  [[nodiscard]] bool ViewedBefore(const TrackedFrame& frame) const;
  bool TrackWithMotion(TrackedFrame& frame);
  bool TrackReferenceKeyFrame(TrackedFrame& frame);
  int OptimizeFramePose(TrackedFrame& frame);
  bool TrackLocalMap(TrackedFrame& frame, int* matches);
  bool NeedKeyFrame(const TrackedFrame& frame, int inliers) const;
  // New keyframe from the frame; points from depth for close keypoints (all when asked).
  KeyFrameHandle CreateKeyFrame(TrackedFrame& frame, bool all_depth_points = false);
  void CullRecentPoints(KeyFrameHandle current);
  struct NewPoint {
    KeyFrameHandle neighbour;
    uint32_t i1 = 0, i2 = 0;  // keypoints in the new keyframe and in the neighbour
    Eigen::Vector3d X_world;
  };
  // Matches and triangulates against copies of the neighbours (no lock needed).
  [[nodiscard]] std::vector<NewPoint> FindNewPoints(const std::vector<KeyFrame>& snapshot,
                                                    const std::vector<KeyFrameHandle>& neighbours,
                                                    std::pair<double, double> depth_range) const;
  // Depths (metres) where new points of a keyframe may lie, from the points it already sees.
  [[nodiscard]] std::pair<double, double> SceneDepthRange(KeyFrameHandle keyframe) const;
  void AddNewPoints(KeyFrameHandle current, const std::vector<NewPoint>& candidates);
  void Fuse(KeyFrameHandle current);
  void LocalBundleAdjustment(KeyFrameHandle current);
  void CullKeyFrames(KeyFrameHandle current);
  [[nodiscard]] double CloseDepth() const;
  void EraseKeyFrame(KeyFrameHandle kf);  // map and keyframe database; remembers the parent
  // A tracked frame's pose through its reference keyframe, or through the parents of culled ones.
  [[nodiscard]] Eigen::Isometry3d ResolveFramePose(const FramePose& f) const;

  // Place recognition (loop_closing.cc).
  void ComputeBow(TrackedFrame& frame) const;
  bool Relocalize(TrackedFrame& frame);
  // Called by local mapping for each keyframe: indexes it, and detects and corrects a loop.
  void DetectAndCloseLoop(KeyFrameHandle keyframe);
  struct LoopMatch;
  bool VerifyLoop(KeyFrameHandle current, KeyFrameHandle candidate, LoopMatch* out);
  void CorrectLoop(KeyFrameHandle current, const LoopMatch& match);
  // Runs on its own thread after the loops-th loop closure; dropped if another loop came meanwhile.
  void GlobalBundleAdjustment(size_t loops);

  Calibration calibration_;
  SlamOptions options_;
  OrbExtractor extractor_;
  mutable ObjectPool<ImagePyramid> pyramids_;  // Extract's work pyramids, reused across frames
  CameraGeometry geometry_;
  StereoDepthRule stereo_depth_;  // which stereo observations optimization keeps as stereo
  MapScales map_scales_;

  mutable std::mutex map_mutex_;  // guards map_ and the mapping bookkeeping below
  Map map_;

  // Tracking state (serial stage only).
  TrackingState state_ = TrackingState::kNotInitialized;
  std::optional<TrackedFrame> last_frame_;
  std::optional<Eigen::Isometry3d> velocity_;  // T_cur_last of the previous step
  KeyFrameHandle reference_keyframe_;
  size_t last_keyframe_frame_ = 0;
  size_t segment_keyframes_ = 0;  // keyframes made since the current map segment started
  std::vector<KeyFrameHandle> local_keyframes_;
  std::vector<PointHandle> local_points_;
  int last_inliers_ = 0;   // of the last frame's local-map tracking
  size_t next_frame_ = 0;  // input index after the last frame tracked (under map_mutex_)
  // One per tracked frame, for the trajectory (written by Track under map_mutex_). Fixed chunks
  // that never move: no doubling's unused half in a long session, and a checkpoint reads them
  // through a view without copying (CaptureState).
  ChunkLog<FramePose> frame_poses_;
  KeyFrameHandle first_keyframe_;
  std::optional<TrackedFrame> init_frame_;  // monocular: first frame of the two-view initialization
  std::mt19937_64 rng_;

  // Mapping bookkeeping (under map_mutex_).
  std::vector<PointHandle> recent_points_;
  MappingTimes mapping_times_;  // written by local mapping only
  // Local mapping's buffers, kept between keyframes so their capacity is reused (mapping only).
  std::vector<KeyFrame> mapping_snapshot_;
  MapBundleAdjustment local_ba_;
  BundleAdjustmentWorkspace local_ba_workspace_;
  std::atomic<int> pending_keyframes_{0};
  mutable std::atomic<bool> keyframe_wanted_{false};

  // Place recognition (database under map_mutex_; loop state used by local mapping only).
  KeyFrameDatabase database_;
  int lost_frames_ = 0;
  bool force_lost_ = false;
  bool allow_new_segments_ = true;  // false on an adopted map and in localization-only mode
  bool map_corrected_ = false;      // a loop correction moved keyframes: refresh the last frame's pose
  // Bumped whenever the whole map moves (loop correction, global BA): work computed on a copy
  // from an older epoch (local BA, new points) is dropped instead of written back.
  uint64_t map_epoch_ = 0;
  CulledKeyFrames culled_;
  struct ConsistentGroup {
    std::vector<KeyFrameHandle> keyframes;
    int count = 0;
  };
  std::vector<ConsistentGroup> consistent_groups_;
  size_t keyframes_since_loop_ = 0;
  std::vector<LoopClosure> loop_closures_;
  std::mt19937_64 loop_rng_;
  std::function<void(std::function<void()>)> background_;
  std::atomic<bool> global_ba_running_{false};
  std::atomic<bool> abandon_background_{false};
  std::function<void(const std::string&)> warning_sink_;
  void Warn(const std::string& message) const;
};

}  // namespace flatslam
