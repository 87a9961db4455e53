// What a user configures for a SLAM session: the options of every system, with the values left
// to the camera (0 or -1) filled in by ResolvedOptions from the calibration.
// Concurrency: plain values and pure functions.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "frontend/orb_extractor.h"
#include "frontend/stereo_matcher.h"
#include "geometry/camera.h"
#include "io/calibration.h"
#include "matching/matcher.h"
#include "optimization/bundle_adjustment.h"
#include "optimization/pose_optimizer.h"

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
  int min_init_points = 150;       // keypoints with depth needed to start a map (stereo/RGB-D)
  int min_init_matches = 100;      // monocular: matches between the two initial frames
  float mono_search_radius = 15;   // monocular: projection search radius, pixels x level scale
  uint64_t seed = 1;               // RANSAC of the monocular initialization
  int min_motion_inliers = 10;     // after frame-to-frame tracking
  int min_local_map_inliers = 30;  // after tracking the local map
  // The motion-model search: with fewer matches it is retried twice as wide, then given up for the
  // reference-keyframe search, which needs min_reference_matches (else: relocalization).
  int min_motion_matches = 20;
  int min_reference_matches = 15;
  // Best/second-best ratio of its search by words (ORB-SLAM2's 0.7), made beside the projection
  // search around the last pose (the pose with more inliers wins).
  float reference_bow_ratio = 0.7f;
  // The keyframe rule (ORB-SLAM2's): a frame is thin when it tracks fewer than this share of its
  // reference keyframe's points (monocular: the _mono share, as forward motion thins points
  // faster), or, with depth, tracks fewer than keyframe_close_tracked close points while
  // keyframe_close_untracked more are untracked; a thin frame with at least keyframe_min_inliers
  // inliers becomes a keyframe when mapping is idle or a timeout or weakness calls for one.
  double keyframe_track_ratio = 0.75;
  double keyframe_track_ratio_mono = 0.9;
  int keyframe_close_tracked = 100;
  int keyframe_close_untracked = 70;
  int keyframe_min_inliers = 15;
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
  // A point made in the last three keyframes is dropped when tracking matched it on fewer than this
  // share of the frames that should have seen it.
  double recent_point_min_found_ratio = 0.25;
  // Revisits: when an older keyframe (not one of the last 20 made) already views the scene from
  // within this fraction of the median scene depth, with its optical axis within 20 degrees, a
  // keyframe is made only if tracking is weak (under half the reference keyframe's points, or
  // under 50 close points). Keeps the map from growing while a place is revisited; 0 = off.
  double revisit_radius = 0.1;
  int revisit_recent_keyframes = 20;  // the newest keyframes never count as an earlier view
  double revisit_max_angle_deg = 20;  // optical axes within this angle view the same scene
  uint32_t agent = 0;                 // stamped on every keyframe (multi-agent maps)
  bool localization_only = false;     // track against the map without changing it (no keyframes)
  // Place recognition. Without a vocabulary there is no relocalization and no loop closing.
  const Vocabulary* vocabulary = nullptr;  // must outlive the session
  bool loop_closing = true;
  bool global_bundle_adjustment = true;     // after each loop correction, in the background
  int relocalization_frames = 10;           // lost frames spent relocalizing before a new map segment starts
  int relocalization_candidates = 20;       // best place-index candidates tried per lost frame
  int relocalization_min_bow_matches = 15;  // bag-of-words matches to a candidate before PnP
  // EPnP RANSAC on those matches (OpenCV's): iterations, reprojection gate in pixels, and the
  // inliers a candidate's pose needs before it is optimized (ORB-SLAM2's PnP solver: 300
  // iterations, chi-square 5.991 at level 0, 10 inliers).
  int relocalization_ransac_iterations = 200;
  float relocalization_ransac_px = 6.0f;
  int relocalization_min_pnp_inliers = 10;
  // Essential graph (loop correction, map merge): covisible keyframes sharing at least this many
  // points are joined by an edge (ORB-SLAM2's 100).
  int essential_graph_min_covisibility = 100;
  int loop_consistency = 3;     // consecutive keyframes that must agree on a loop
  int loop_min_keyframes = 10;  // keyframes in the map, and made since the last loop, before a loop search
  int min_loop_matches = 40;    // map points matched across the loop after the Sim(3)/SE(3) search
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

// The options a session for this calibration runs with: values left to the camera or sensor (0 or -1
// above) filled in, the monocular search radius in place of the motion one. Each value filled in
// is listed in *derived (when given) with its rule.
[[nodiscard]] SlamOptions ResolvedOptions(const SlamOptions& options, const Calibration& calibration,
                                          std::vector<DerivedOption>* derived = nullptr);

// Features per image for a camera: 1.9 x sqrt(width x height), times sqrt(20 Hz / frame rate)
// below 20 Hz, rounded to the 1-1.2-1.5-2-2.5-3-4-5-6-8 series and kept in [500, 8000].
[[nodiscard]] int DerivedFeatureBudget(const PinholeCamera& camera, double frame_rate_hz);

}  // namespace flatslam
