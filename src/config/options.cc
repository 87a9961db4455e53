#include "config/options.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <vector>

#include "config/context.h"
#include "core/error.h"
#include "core/requirements.h"

namespace flatslam {

std::string SlamOptions::Problem() const {
  OrbOptions orb_checked = orb;
  if (orb_checked.features == 0) orb_checked.features = 1;  // 0 = derived from the camera
  Requirements r;
  r.Nested("orb", orb_checked.Problem());
  r.Nested("stereo", stereo.Problem());
  r.Nested("matcher", matcher.Problem());
  r.Nested("pose", pose.Problem());
  r.Nested("bundle_adjustment", bundle_adjustment.Problem());
  const std::string own = FieldsProblem();
  r.Require(own.empty(), own);
  return r.first();
}

int DerivedFeatureBudget(const PinholeCamera& camera, double frame_rate_hz) {
  // 1.9 features per pixel of the image's linear size (the square root of its area). The budget a
  // camera needs follows its linear size, not its area: the scene holds about as many trackable
  // corners at any resolution (the pyramid finds them at coarser levels), while the image motion
  // they must be found across grows with the size. 1.9 is the middle of the range of coefficients
  // (1.82-1.98) for which the rule returns ORB-SLAM's published budgets for 640x480, 752x480 and
  // 1241x376 at 10 Hz (1000, 1200, 2000). Below 20 Hz the scene moves further between frames
  // and fewer keypoints survive from one frame to the next: the budget grows with
  // sqrt(20 / rate), halfway (in log terms) between no growth and growth with the image motion
  // per frame.
  const double rate = frame_rate_hz > 0 ? frame_rate_hz : 20.0;
  const double raw =
      1.9 * std::sqrt(static_cast<double>(camera.width) * camera.height) * std::sqrt(std::max(1.0, 20.0 / rate));
  // Nearest value of the 1-1.2-1.5-2-2.5-3-4-5-6-8 series (in log terms), so that cameras of
  // nearly the same size share a budget.
  static constexpr double kSeries[] = {1, 1.2, 1.5, 2, 2.5, 3, 4, 5, 6, 8, 10};
  const double decade = std::pow(10.0, std::floor(std::log10(std::max(raw, 1.0))));
  double best = decade;
  for (double m : kSeries)
    if (std::abs(std::log(m * decade / raw)) < std::abs(std::log(best / raw))) best = m * decade;
  return static_cast<int>(std::clamp<long>(std::lround(best), kMinDerivedFeatures, kMaxDerivedFeatures));
}

double ThinKeyFrameParallaxDeg(const PinholeCamera& camera) { return 4.0 / camera.fx * 180.0 / M_PI; }

int MonocularKeyFrameSpacing(double frame_rate_hz) {
  // A monocular keyframe waits 2 frames after the last (set at KITTI's 10 Hz, 0.2 s): keyframes
  // from consecutive frames add little parallax while forward motion thins the tracked points.
  // At a lower rate 2 frames span more: at 5 Hz a forward-moving camera's points leave the view
  // before a keyframe 0.4 s on can triangulate new ones (KITTI 06 and 07 with every 2nd frame
  // lost 11 frames each, 0 with 1 frame). The spacing therefore stays near 0.2 s where 2 frames
  // are longer. It is not stretched to 0.2 s at higher rates: 4 frames at 20 Hz and 6 at 30 Hz
  // lost the hand-held view sooner and cost EuRoC and the hand-held scene accuracy.
  if (!(frame_rate_hz > 0)) return 2;
  return static_cast<int>(std::clamp(std::lround(0.2 * frame_rate_hz), 1L, 2L));
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
                  "1.9 x sqrt(%d x %d) (the image's linear size), x sqrt(20 Hz / %.3g Hz) below 20 Hz, "
                  "rounded to the 1-1.2-1.5-2-2.5-3-4-5-6-8 series",
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
    o.min_frames_between_keyframes = mono ? MonocularKeyFrameSpacing(rate) : 0;
    if (mono) {
      std::snprintf(text, sizeof(text),
                    "monocular: 2 frames, or fewer where 2 frames span more than 0.2 s: the frames nearest to "
                    "0.2 s at %.3g Hz, at least 1",
                    rate);
      note("min_frames_between_keyframes", text);
    } else {
      note("min_frames_between_keyframes", "with depth: 0, an idle local mapping takes any keyframe");
    }
  }
  if (o.min_parallax_deg == 0) {
    o.min_parallax_deg = mono ? kMonocularParallaxDeg : kDepthParallaxDeg;
    if (mono)
      std::snprintf(text, sizeof(text), "monocular: %g degrees, depth within about 4%% at a pixel of noise",
                    kMonocularParallaxDeg);
    else
      std::snprintf(text, sizeof(text), "with depth: %g degrees; close points take the measured depth",
                    kDepthParallaxDeg);
    note("min_parallax_deg", text);
  }
  if (o.thin_keyframe_parallax_deg == 0) {
    // The rays of a point whose depth comes out within about 25% at a pixel of keypoint noise:
    // a ray is measured to 1 / fx rad, so 4 / fx rad of parallax. These points are taken only so
    // that tracking keeps enough of them through a turn into an unmapped view, where the camera
    // turns more than it moves; later keyframes widen their rays and local BA refines them.
    if (mono) {
      o.thin_keyframe_parallax_deg = std::min(ThinKeyFrameParallaxDeg(cam), o.min_parallax_deg);
      std::snprintf(text, sizeof(text),
                    "monocular: the angle of 4 pixels, 4 / fx = 4 / %.4g rad (depth within about 25%% at a pixel of "
                    "noise), at most min_parallax_deg, for keyframes that would hold too few points to track",
                    cam.fx);
      note("thin_keyframe_parallax_deg", text);
    } else {
      o.thin_keyframe_parallax_deg = o.min_parallax_deg;
      note("thin_keyframe_parallax_deg", "with depth: min_parallax_deg (off): points under it take the measured depth");
    }
  }
  if (o.thin_keyframe_points == 0) {
    // Through a fast turn the points a keyframe tracks halve within a few frames (the hand-held
    // glance: 180 -> 77 in six frames, with a keyframe every second frame), so a keyframe waiting
    // until it holds the fading count takes its narrow rays too late to be tracked.
    o.thin_keyframe_points = 2 * o.keyframe_fading_inliers;
    note("thin_keyframe_points",
         "twice keyframe_fading_inliers: the points a keyframe tracks through a fast turn halve within a few frames");
  }
  return o;
}

double SystemContext::CloseDepth(std::span<const float> depth) const {
  const double fixed = CloseDepth();
  if (monocular()) return fixed;
  std::vector<float>& measured = MeasuredDepths(depth);
  if (measured.size() <= kNearestCloseKeypoints) return fixed;
  // Keypoints nearer than the returned depth are close: the kNearestCloseKeypoints nearest at least.
  std::nth_element(measured.begin(), measured.begin() + kNearestCloseKeypoints, measured.end());
  return std::max<double>(fixed, measured[kNearestCloseKeypoints]);
}

SystemContext::SystemContext(const Calibration& calibration_in, const SlamOptions& resolved,
                             const ScalePyramid& pyramid)
    : calibration(calibration_in), options(resolved) {
  const std::string problem = options.Problem();
  FLATSLAM_CHECK(problem.empty(), "invalid SLAM options: ", problem, " does not hold");
  FLATSLAM_CHECK(calibration.camera.valid(), "invalid camera calibration");
  FLATSLAM_CHECK(calibration.sensor != Sensor::kStereo || calibration.baseline_m > 0,
                 "stereo calibration without a baseline");
  geometry = CameraGeometry::FromCalibration(calibration, options.rgbd_virtual_baseline_m, pyramid);
  map_scales.scale_factor = geometry.pyramid.scale_factor;
  map_scales.levels = geometry.pyramid.levels;
  stereo_depth = StereoDepthRule::ForRig(calibration.sensor == Sensor::kStereo, calibration.baseline_m,
                                         options.far_stereo_baselines, options.far_stereo_level_px);
}

}  // namespace flatslam
