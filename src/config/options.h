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

// The SLAM systems' own options: X(type, name, default, requirement, description)
// (core/option_fields.h). A value 0 or -1 that the description calls "by sensor" or "the frame
// rate" is filled in by ResolvedOptions.
#define FLATSLAM_SLAM_OPTIONS(X)                                                                                      \
  X(double, rgbd_virtual_baseline_m, 0.08, rgbd_virtual_baseline_m > 0,                                               \
    "RGB-D depth becomes a stereo measurement with this baseline (metres)")                                           \
  X(double, close_depth_baselines, 35, close_depth_baselines > 0,                                                     \
    "\"close\" points (reliable stereo depth) are nearer than this x baseline: created from one frame, counted "      \
    "for keyframe decisions and culling; ORB-SLAM2 uses 35 for KITTI and EuRoC, 40 for TUM. New points and the "      \
    "keyframe rule take at least a frame's 100 nearest keypoints as close (SystemContext::CloseDepth)")               \
  X(double, far_stereo_baselines, kFarStereoBaselines, far_stereo_baselines >= 0,                                     \
    "stereo keypoints deeper than this x baseline count as monocular observations in pose optimization and "          \
    "bundle adjustment (0: never): their disparity is a few pixels, where a tenth of a pixel of rectification "       \
    "error is a percent of depth, and it biased the trajectory's scale (KITTI 06: 0.4% too long with them); they "    \
    "still give rotation, and depth once triangulated over keyframes. 35 is ORB-SLAM2's close-depth threshold for "   \
    "KITTI and EuRoC. A frame whose median measured depth lies beyond it keeps stereo up to that median (the scale "  \
    "needs them)")                                                                                                    \
  X(double, far_stereo_level_px, kFarStereoLevelPixels, far_stereo_level_px >= 0,                                     \
    "stereo keypoints whose disparity is under this many pixels of their pyramid level count as monocular "           \
    "observations too (0: never): there the sub-pixel step of stereo matching pulls the disparity towards zero, "     \
    "depths long; with them a rig short for its scene lost scale (EuRoC's camera on a motorway: 4% short)")           \
  X(int, min_init_points, 150, min_init_points > 0, "keypoints with depth needed to start a map (stereo/RGB-D)")      \
  X(int, min_init_matches, 100, min_init_matches > 0, "monocular: matches between the two initial frames")            \
  X(float, init_search_px, 100, init_search_px > 0,                                                                   \
    "monocular: pixels around a keypoint of the first frame searched for its match in the second (ORB-SLAM2's "       \
    "100; the two frames are close in time)")                                                                         \
  X(float, mono_search_radius, 15, mono_search_radius > 0,                                                            \
    "monocular: projection search radius, pixels x level scale")                                                      \
  X(uint64_t, seed, 1, true, "RANSAC of the monocular initialization")                                                \
  X(int, min_motion_inliers, 10, min_motion_inliers > 0, "inliers needed after frame-to-frame tracking")              \
  X(int, min_local_map_inliers, 30, min_local_map_inliers > 0, "inliers needed after tracking the local map")         \
  X(int, min_motion_matches, 20, min_motion_matches > 0,                                                              \
    "the motion-model search: with fewer matches it is retried twice as wide, then given up for the "                 \
    "reference-keyframe search")                                                                                      \
  X(int, min_reference_matches, 15, min_reference_matches > 0,                                                        \
    "matches the reference-keyframe search needs (else: relocalization)")                                             \
  X(float, reference_bow_ratio, 0.7f, reference_bow_ratio > 0 && reference_bow_ratio <= 1,                            \
    "best/second-best ratio of the reference search by words (ORB-SLAM2's 0.7), made beside the projection search "   \
    "around the last pose (the pose with more inliers wins)")                                                         \
  X(double, keyframe_track_ratio, 0.75, keyframe_track_ratio > 0 && keyframe_track_ratio <= 1,                        \
    "the keyframe rule (ORB-SLAM2's): a frame is thin when it tracks fewer than this share of its reference "         \
    "keyframe's points, or, with depth, tracks fewer than keyframe_close_tracked close points while "                 \
    "keyframe_close_untracked more are untracked; a thin frame with at least keyframe_min_inliers inliers becomes a " \
    "keyframe when mapping is idle or a timeout or weakness calls for one")                                           \
  X(double, keyframe_track_ratio_mono, 0.9, keyframe_track_ratio_mono > 0 && keyframe_track_ratio_mono <= 1,          \
    "keyframe_track_ratio for monocular input: forward motion thins points faster")                                   \
  X(int, keyframe_close_tracked, 100, keyframe_close_tracked >= 0, "see keyframe_track_ratio")                        \
  X(int, keyframe_close_untracked, 70, keyframe_close_untracked >= 0, "see keyframe_track_ratio")                     \
  X(int, keyframe_min_inliers, 15, keyframe_min_inliers >= 0, "see keyframe_track_ratio")                             \
  X(double, keyframe_weak_ratio, 0.25, keyframe_weak_ratio >= 0 && keyframe_weak_ratio <= 1,                          \
    "with depth, a frame tracking under this share of its reference keyframe's points is weak: a keyframe even "      \
    "while mapping is busy (ORB-SLAM2's 0.25)")                                                                       \
  X(double, keyframe_fading_ratio, 0.5, keyframe_fading_ratio >= 0 && keyframe_fading_ratio <= 1,                     \
    "monocular: tracking fades under this share of the reference keyframe's points, or under "                        \
    "keyframe_fading_inliers inliers; busy mapping is then asked to finish early. With depth: a frame "               \
    "tracking under this share of the most inliers a frame tracked since the last keyframe is thin")                  \
  X(int, keyframe_fading_inliers, 100, keyframe_fading_inliers >= 0, "see keyframe_fading_ratio")                     \
  X(float, motion_search_radius, 7, motion_search_radius > 0,                                                         \
    "pixels (x level scale) searched around a point's predicted position")                                            \
  X(int, max_frames_between_keyframes, 0, max_frames_between_keyframes >= 0, "0 = the frame rate (one second)")       \
  X(int, min_frames_between_keyframes, -1, min_frames_between_keyframes >= -1,                                        \
    "an idle local mapping takes a keyframe only this many frames after the last; -1 = by sensor (monocular: 2, "     \
    "or 1 below 7.5 Hz, see MonocularKeyFrameSpacing; 0 with depth)")                                                 \
  X(size_t, local_keyframes, 10, local_keyframes > 0, "covisible keyframes used for triangulation")                   \
  X(double, new_point_depth_factor, 4, new_point_depth_factor >= 1,                                                   \
    "new points of a keyframe are searched between the near depth of the points it sees (5th percentile) "            \
    "divided by this and the far one (95th) times this: the same scene, with room both ways")                         \
  X(double, min_parallax_deg, 0, min_parallax_deg >= 0 && min_parallax_deg < 90,                                      \
    "least angle between the rays of a point triangulated from two keyframes; 0 = by sensor: 2 deg monocular "        \
    "(depth within about 4% at a pixel of noise; on KITTI 07 it also keeps out cars driving ahead, whose features "   \
    "look like points at infinity), 1.146 deg (ORB-SLAM2's cos 0.9998) with depth, where close points come from "     \
    "the stereo or depth measurement")                                                                                \
  X(double, thin_keyframe_parallax_deg, 0, thin_keyframe_parallax_deg >= 0 && thin_keyframe_parallax_deg < 90,          \
    "monocular: a keyframe that would hold fewer points than thin_keyframe_points also takes new points whose "     \
    "rays diverge by at least this angle, under min_parallax_deg, in the cells of an 8 x 8 grid over its image "     \
    "where it holds no point, widest first, up to that count; 0 = from the "                                        \
    "camera: the angle of 4 pixels (4 / fx rad: depth within about 25% at a pixel of noise), at most "              \
    "min_parallax_deg; off with depth (min_parallax_deg)")                                                           \
  X(int, thin_keyframe_points, 0, thin_keyframe_points >= 0,                                                          \
    "points (tracked and new) a monocular keyframe holds before it takes the narrow rays of "                       \
    "thin_keyframe_parallax_deg; 0 = twice keyframe_fading_inliers")                                                 \
  X(size_t, max_local_map_keyframes, 80, max_local_map_keyframes > 0, "keyframes whose points are tracked")           \
  X(size_t, max_local_ba_keyframes, 20, max_local_ba_keyframes > 0,                                                   \
    "free keyframes of local BA: the new one and its strongest covisible; bounds a keyframe's cost where far points " \
    "make every recent keyframe covisible (fast forward motion); the rest of their observers still enter as fixed "   \
    "poses")                                                                                                          \
  X(double, redundant_keyframe_ratio, 0.9, redundant_keyframe_ratio > 0 && redundant_keyframe_ratio <= 1,             \
    "a keyframe is culled when this share of its points is seen by 3 others")                                         \
  X(double, recent_point_min_found_ratio, 0.25,                                                                       \
    recent_point_min_found_ratio >= 0 && recent_point_min_found_ratio <= 1,                                           \
    "a point made in the last three keyframes is dropped when tracking matched it on fewer than this share of the "   \
    "frames that should have seen it")                                                                                \
  X(double, revisit_radius, 0.1, revisit_radius >= 0,                                                                 \
    "revisits: when an older keyframe already views the scene from within this fraction of the median scene depth, "  \
    "with its optical axis within revisit_max_angle_deg, a keyframe is made only if tracking is weak (under half "    \
    "the reference keyframe's points, or under 50 close points); keeps the map from growing while a place is "        \
    "revisited; 0 = off")                                                                                             \
  X(int, revisit_recent_keyframes, 20, revisit_recent_keyframes >= 0,                                                 \
    "the newest keyframes made never count as an earlier view")                                                       \
  X(double, revisit_max_angle_deg, 20, revisit_max_angle_deg > 0 && revisit_max_angle_deg <= 180,                     \
    "optical axes within this angle view the same scene")                                                             \
  X(double, revisit_healthy_ratio, 0.5, revisit_healthy_ratio >= 0 && revisit_healthy_ratio <= 1,                     \
    "a revisit makes no keyframe while tracking keeps this share of the reference keyframe's points and "             \
    "revisit_healthy_close close points")                                                                             \
  X(int, revisit_healthy_close, 50, revisit_healthy_close >= 0, "see revisit_healthy_ratio")                          \
  X(bool, loop_closing, true, true, "detect and close loops (needs a vocabulary)")                                    \
  X(bool, global_bundle_adjustment, true, true, "after each loop correction, in the background")                      \
  X(int, relocalization_frames, 10, relocalization_frames >= 0,                                                       \
    "lost frames spent relocalizing before a new map segment starts")                                                 \
  X(int, relocalization_candidates, 20, relocalization_candidates > 0,                                                \
    "best place-index candidates tried per lost frame")                                                               \
  X(int, relocalization_min_bow_matches, 15, relocalization_min_bow_matches >= 3,                                     \
    "bag-of-words matches to a candidate before PnP")                                                                 \
  X(int, relocalization_ransac_iterations, 200, relocalization_ransac_iterations > 0,                                 \
    "EPnP RANSAC iterations on those matches (ORB-SLAM2's PnP solver: 300)")                                          \
  X(float, relocalization_ransac_px, 6.0f, relocalization_ransac_px > 0,                                              \
    "EPnP RANSAC reprojection gate in pixels (ORB-SLAM2: chi-square 5.991 at level 0)")                               \
  X(int, relocalization_min_pnp_inliers, 10, relocalization_min_pnp_inliers >= 4,                                     \
    "inliers a candidate's PnP pose needs before it is optimized (ORB-SLAM2: 10)")                                    \
  X(int, essential_graph_min_covisibility, 100, essential_graph_min_covisibility > 0,                                 \
    "essential graph (loop correction): covisible keyframes sharing at least this many points are joined by an "      \
    "edge (ORB-SLAM2's 100)")                                                                                         \
  X(int, loop_consistency, 3, loop_consistency >= 1, "consecutive keyframes that must agree on a loop")               \
  X(int, loop_min_keyframes, 10, loop_min_keyframes >= 0,                                                             \
    "keyframes in the map, and made since the last loop, before a loop search")                                       \
  X(int, min_loop_matches, 40, min_loop_matches >= 3,                                                                 \
    "map points matched across the loop after the Sim(3)/SE(3) search")

struct SlamOptions {
  // Extraction; orb.features 0 = derived from the camera (see ResolvedOptions).
  OrbOptions orb = SlamOrbDefaults();
  StereoOptions stereo;
  MatcherOptions matcher;
  PoseOptimizerOptions pose;
  BundleAdjustmentOptions bundle_adjustment;
  FLATSLAM_SLAM_OPTIONS(FLATSLAM_OPTION_FIELD)
  // Not settable by name.
  uint32_t agent = 0;              // stamped on every keyframe (multi-agent maps)
  bool localization_only = false;  // track against the map without changing it (no keyframes)
  // Place recognition. Without a vocabulary there is no relocalization and no loop closing.
  const Vocabulary* vocabulary = nullptr;             // must outlive the session
  InjectedFault inject_fault = InjectedFault::kNone;  // tests only (see InjectedFault)

  FLATSLAM_OPTION_MEMBERS(FLATSLAM_SLAM_OPTIONS)
  // Every settable field, nested ones first with their struct's prefix ("orb.features"):
  // visit(key, field&, description).
  template <class Visit>
  void VisitAll(Visit&& visit) {
    auto nested = [&](const char* prefix, auto& options) {
      options.VisitFields([&](const char* name, auto& field, const char* description) {
        visit(std::string(prefix) + "." + name, field, description);
      });
    };
    nested("orb", orb);
    nested("stereo", stereo);
    nested("matcher", matcher);
    nested("pose", pose);
    nested("bundle_adjustment", bundle_adjustment);
    VisitFields(
        [&](const char* name, auto& field, const char* description) { visit(std::string(name), field, description); });
  }

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

// The range a derived feature budget is kept in.
inline constexpr int kMinDerivedFeatures = 500, kMaxDerivedFeatures = 8000;
// Ray parallax below which two keyframes do not triangulate a new point (min_parallax_deg = 0):
// monocular 2 degrees (depth within about 4% at a pixel of noise); with depth ORB-SLAM2's
// 1.146 degrees (cos 0.9998), as close points take the measured depth.
inline constexpr double kMonocularParallaxDeg = 2.0, kDepthParallaxDeg = 1.146;
// Features per image for a camera: 1.9 x sqrt(width x height), times sqrt(20 Hz / frame rate)
// below 20 Hz, rounded to the 1-1.2-1.5-2-2.5-3-4-5-6-8 series and kept in [500, 8000].
[[nodiscard]] int DerivedFeatureBudget(const PinholeCamera& camera, double frame_rate_hz);

// Parallax of the narrow rays a thin monocular keyframe takes (thin_keyframe_parallax_deg = 0):
// the angle of 4 pixels of the camera, 4 / fx rad, in degrees.
[[nodiscard]] double ThinKeyFrameParallaxDeg(const PinholeCamera& camera);

// Frames a monocular keyframe waits after the last: 2, or the number nearest to 0.2 s where that
// is fewer (1 below 7.5 Hz); 2 when the frame rate is unknown (<= 0).
[[nodiscard]] int MonocularKeyFrameSpacing(double frame_rate_hz);

}  // namespace flatslam
