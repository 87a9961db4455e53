// Accuracy with defaults only (no feature budget or option set by hand) on the scenes that stress
// what the real snippets do not: a motorway at 25 m/s with most texture 20-200 m away, a hand-held
// camera with fast turns, blur and exposure changes, and moving objects covering up to 30% of the
// view. Thresholds are the bars of the issue on accuracy that holds on unseen cameras and motions;
// docs/STATUS.md gives the measured figures.
#include <algorithm>
#include <cstdio>
#include <string>

#include <gtest/gtest.h>

#include "io/dataset.h"
#include "jobs/slam_runner.h"
#include "place/vocabulary.h"
#include "default_vocabulary.h"
#include "test_data.h"
#include "trajectory_score.h"
#include "trajectory/metrics.h"

namespace flatslam {
namespace {

struct SceneOutcome {
  SlamRunResult run;
  EvalResult se3, sim3;
  double path_m = 0;
  size_t first_tracked = 0;  // first frame with a pose
  size_t lost_after = 0;     // frames without a pose after it
  double rate_hz = 0;
};

SceneOutcome RunWithDefaults(const std::string& spec, std::optional<Sensor> sensor = std::nullopt, uint64_t seed = 0) {
  DatasetOptions dataset_options;
  dataset_options.sensor = sensor;
  const auto dataset = OpenDataset(spec, dataset_options);
  SlamOptions options = testing::OptionsWithDefaultVocabulary();  // everything left to the camera
  if (seed != 0) options.seed = seed;
  SceneOutcome out;
  out.rate_hz = dataset->calibration().frame_rate_hz;
  out.run = RunSlam(*dataset, options, SlamRunOptions{});
  const testing::TrajectoryScore score = testing::ScoreTrajectory(*dataset->ground_truth(), out.run.trajectory);
  out.se3 = score.se3;
  out.sim3 = score.sim3;
  out.path_m = score.path_m;
  out.first_tracked = out.run.reports.size();
  for (const FrameReport& r : out.run.reports)
    if (r.state == TrackingState::kOk) out.first_tracked = std::min(out.first_tracked, r.index);
  for (const FrameReport& r : out.run.reports)
    if (r.index > out.first_tracked && r.state != TrackingState::kOk) ++out.lost_after;
  std::printf(
      "%s (%s): %zu frames, first tracked %zu, %zu lost after, %zu keyframes, ATE %.4f m (%.3f%% of %.1f m), "
      "Sim(3) %.4f m, scale %.4f\n",
      spec.c_str(), SensorName(dataset->calibration().sensor), out.run.reports.size(), out.first_tracked,
      out.lost_after, out.run.keyframe_count, out.se3.ate_m.rmse, 100 * out.se3.ate_m.rmse / out.path_m, out.path_m,
      out.sim3.ate_m.rmse, out.sim3.alignment.scale);
  return out;
}

// The motorway's stereo bars: nothing lost, ATE under 0.5% of the path, scale within 1%.
void ExpectMotorwayBars(const SceneOutcome& o) {
  EXPECT_EQ(o.first_tracked, 0u);
  EXPECT_EQ(o.lost_after, 0u);
  EXPECT_LT(o.se3.ate_m.rmse, 0.005 * o.path_m);
  EXPECT_NEAR(o.sim3.alignment.scale, 1.0, 0.01);
}

// Bar: stereo on the motorway, 60 s.
TEST(SceneAccuracy, HighwayStereo) {
  const SceneOutcome o = RunWithDefaults("synth:highway");
  EXPECT_GT(o.path_m, 1200.0);
  ExpectMotorwayBars(o);
}

// Bar: monocular on the motorway initializes within one second and loses under 1% of frames.
TEST(SceneAccuracy, HighwayMonocular) {
  const SceneOutcome o = RunWithDefaults("synth:highway", Sensor::kMonocular);
  EXPECT_LT(static_cast<double>(o.first_tracked), o.rate_hz);
  EXPECT_LT(static_cast<double>(o.lost_after), 0.01 * o.run.reports.size());
  EXPECT_LT(o.sim3.ate_m.rmse, 0.01 * o.path_m);  // shape, after the arbitrary scale
}

// The first frame after the start has no motion prior. On the motorway with noisy images its two
// searches (around the last pose, and by words against the reference keyframe) found poses 2.5 m
// apart with about as many inliers each, the one at rest won, and every later prediction kept
// its speed: 0 frames lost, trajectories 4.6-30x too short (SE(3) 28.9-35.6 m over 125 m). Now
// each searches around itself and the better supported wins. Bar: the motorway's, over 5 s.
TEST(SceneAccuracy, HighwayStereoWithNoisyImagesKeepsItsSpeedFromTheFirstFrame) {
  for (const char* spec : {"synth:highway:duration=5.1,noise=6", "synth:highway:duration=5.1,noise=7",
                           "synth:highway:duration=5.1,noise=6,rig_error=-0.1"}) {
    SCOPED_TRACE(spec);
    const SceneOutcome o = RunWithDefaults(spec);
    ExpectMotorwayBars(o);
  }
}

// The same start with a small wide camera (672x376, fx 350, a 0.12 m rig: half KITTI's focal
// length). The 2.1 m between the two poses moved a tenth of the matched points only 5.2-6.4
// pixels, under the 7-pixel motion window the fair comparison waited for, so the wide search's
// pose at rest won: 5 s came out 3.19% of the path (scale 1.1216), with noise 22.19% (scale
// 4.0629). The comparison now starts where the poses cannot share inliers: 0.63% (1.0216) and
// 0.88% (0.9723). The motorway's bars (0.5%, 1%) do not hold at this focal length yet (20 s:
// 0.41%, scale 1.0140); these bars separate a kept speed from a lost one.
TEST(SceneAccuracy, HighwayStereoOnASmallWideCameraKeepsItsSpeedFromTheFirstFrame) {
  for (const char* spec : {"synth:highway:duration=5.1,width=672,height=376,fx=350,baseline=0.12",
                           "synth:highway:duration=5.1,width=672,height=376,fx=350,baseline=0.12,noise=6"}) {
    SCOPED_TRACE(spec);
    const SceneOutcome o = RunWithDefaults(spec);
    EXPECT_EQ(o.first_tracked, 0u);
    EXPECT_EQ(o.lost_after, 0u);
    EXPECT_LT(o.se3.ate_m.rmse, 0.02 * o.path_m);
    EXPECT_NEAR(o.sim3.alignment.scale, 1.0, 0.05);
  }
}

// A stereo rig with half the motorway's baseline (0.25 m): 35 baselines are 8.75 m, nearer than
// 70 keypoints of a frame, and keyframes came only from the share of tracked points, 17 m apart;
// the map held almost only points 100 m and more away (10 s: 11 keyframes, 0.73% of the path,
// scale 1.025). The keyframe rule now counts at least a frame's 100 nearest keypoints as close.
// With 0.12 m most of the motorway's matched disparities lie under a pixel of their pyramid level,
// where the sub-pixel step pulls them towards zero; with them in optimization the trajectory came
// out 1.0% short (10 s: 0.7769 m, scale 1.0109). They count as monocular now (far_stereo_level_px):
// 0.2621 m, 1.0035. Bar: the motorway's.
TEST(SceneAccuracy, HighwayStereoWithAShortBaseline) {
  for (const char* spec : {"synth:highway:duration=10,baseline=0.25", "synth:highway:duration=10,baseline=0.12"}) {
    SCOPED_TRACE(spec);
    const SceneOutcome o = RunWithDefaults(spec);
    ExpectMotorwayBars(o);
  }
}

// Every frame tracked from the first on, and the SE(3) ATE under `fraction` of the path.
void ExpectEveryFrameWithin(const SceneOutcome& o, double fraction) {
  EXPECT_EQ(o.first_tracked, 0u);
  EXPECT_EQ(o.lost_after, 0u);
  EXPECT_LT(o.se3.ate_m.rmse, fraction * o.path_m);
}

// Bar: hand-held stereo and RGB-D, 60 s: no frame lost, ATE under 1% of the path.
TEST(SceneAccuracy, HandheldStereo) {
  ExpectEveryFrameWithin(RunWithDefaults("synth:handheld"), 0.01);
}

TEST(SceneAccuracy, HandheldRgbd) {
  ExpectEveryFrameWithin(RunWithDefaults("synth:handheld", Sensor::kRgbd), 0.01);
}

// Bar: monocular hand-held, 60 s: initializes within one second and loses under 1% of frames
// (the fast glances into unmapped parts of the office are where a monocular map can lose itself).
TEST(SceneAccuracy, HandheldMonocular) {
  const SceneOutcome o = RunWithDefaults("synth:handheld", Sensor::kMonocular);
  EXPECT_LT(static_cast<double>(o.first_tracked), o.rate_hz);
  EXPECT_LT(static_cast<double>(o.lost_after), 0.01 * o.run.reports.size());
  EXPECT_LT(o.sim3.ate_m.rmse, 0.01 * o.path_m);  // shape, after the arbitrary scale
}

// The hand-held camera's first glance into an unmapped part of the office, 5 s in: the camera
// turns more than it moves, so keyframes two frames apart have rays under a degree apart, and
// the points a frame tracked fell from about 200 to under 50 in eight frames. With keyframes
// taking narrow rays only once they held fewer than the fading count (100), down to 1.146
// degrees, 14-15 frames were lost at 5 of 6 image noise seeds (10 s runs), a new map segment
// after. Keyframes holding fewer than twice that count now take rays down to the angle of 4
// pixels (thin_keyframe_points, thin_keyframe_parallax_deg). Bar: the monocular hand-held one,
// with nothing lost, at each of four noise seeds.
TEST(SceneAccuracy, HandheldMonocularKeepsTrackingThroughAGlanceIntoTheUnmapped) {
  for (int seed = 1; seed <= 4; ++seed) {
    SCOPED_TRACE(seed);
    const SceneOutcome o = RunWithDefaults("synth:handheld:duration=10,seed=" + std::to_string(seed), Sensor::kMonocular);
    EXPECT_LT(static_cast<double>(o.first_tracked), o.rate_hz);
    EXPECT_EQ(o.lost_after, 0u);
    EXPECT_LT(o.sim3.ate_m.rmse, 0.01 * o.path_m);
  }
}

// Moving objects covering up to 30% of the view: each sensor keeps tracking and stays within the
// accuracy bars of the static room (1% of path with depth, 2% monocular after Sim(3)).
TEST(SceneAccuracy, DynamicRoomEverySensor) {
  for (const Sensor sensor : {Sensor::kStereo, Sensor::kRgbd, Sensor::kMonocular}) {
    const SceneOutcome o = RunWithDefaults("synth:room:dynamic=0.3,duration=30", sensor);
    SCOPED_TRACE(SensorName(sensor));
    EXPECT_LT(static_cast<double>(o.lost_after), 0.01 * o.run.reports.size());
    if (sensor == Sensor::kMonocular) {
      EXPECT_LT(static_cast<double>(o.first_tracked), o.rate_hz);
      EXPECT_LT(o.sim3.ate_m.rmse, 0.02 * o.path_m);
    } else {
      EXPECT_EQ(o.first_tracked, 0u);
      EXPECT_LT(o.se3.ate_m.rmse, 0.01 * o.path_m);
    }
  }
}

// With depth, a keyframe comes before tracking fades, also where the view turns to what the
// reference keyframe's points (seen by one or two keyframes yet) cannot measure and nothing lies
// nearer than the close depth: the room's RGB-D camera at 320x240 (its close depth, 2.8 m, is
// nearer than most of the room), and the hand-held RGB-D camera at 10 Hz, whose glances leave the
// last keyframe's view within a few frames. Both lost tracking before (33 and 22 frames).
TEST(SceneAccuracy, DepthCamerasMakeKeyFramesBeforeTrackingFades) {
  for (const char* spec : {"synth:room:width=320,height=240,fx=260,duration=30", "synth:handheld:fps=10"}) {
    SCOPED_TRACE(spec);
    const SceneOutcome o = RunWithDefaults(spec, Sensor::kRgbd);
    ExpectEveryFrameWithin(o, 0.01);
    EXPECT_EQ(
        std::count_if(o.run.reports.begin(), o.run.reports.end(), [](const FrameReport& r) { return r.reinitialized; }),
        0);
  }
}

// RGB-D depth as a structured-light sensor reads it (quantized, the projector's shadows beside
// nearer edges, edges fattened and registered 1 px off the colour image): no frame lost, ATE under
// a tenth of the other scene tests' 1% of the path (20 s: 0.0061 m, 0.05% of 12 m, against 0.0048 m
// on exact depth) and the scale within 1% (1.0015). On the full scenes (bench/accuracy_table.sh):
// room 0.0072 -> 0.0147 m, hand-held 0.0040 -> 0.0050 m, none lost.
TEST(SceneAccuracy, RgbdTracksOnStructuredLightDepth) {
  const SceneOutcome o = RunWithDefaults("synth:handheld:structured_light=1,duration=20", Sensor::kRgbd);
  ExpectEveryFrameWithin(o, 0.001);
  EXPECT_NEAR(o.sim3.alignment.scale, 1.0, 0.01);
}

}  // namespace
}  // namespace flatslam
