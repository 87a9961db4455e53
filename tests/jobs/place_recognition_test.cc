// End-to-end place recognition: loop closure on synthetic loops (stereo, RGB-D, monocular),
// relocalization after a kidnapping (dropped frames) and after forced loss on real KITTI data,
// and no false loop on the KITTI 07 snippet. Loops are checked against ground truth: a closure
// is true when both keyframes' true camera centres are close.
#include <algorithm>
#include <cstdio>

#include <gtest/gtest.h>

#include "jobs/slam_runner.h"
#include "place/vocabulary.h"
#include "default_vocabulary.h"
#include "test_data.h"
#include "trajectory_score.h"
#include "trajectory/metrics.h"

namespace flatslam {
namespace {

using testing::DefaultVocabulary;

struct PlaceOutcome {
  SlamRunResult run;
  Trajectory gt;
  EvalResult se3, sim3;
  double path_m = 0;
  size_t lost = 0, relocalized = 0, reinitialized = 0;
  int false_loops = 0;
};

PlaceOutcome RunScenario(const std::string& spec, bool loop_closing, const SlamRunOptions& run = {}, int features = 1000) {
  const auto dataset = OpenDataset(spec);
  SlamOptions options;
  options.orb.features = features;
  options.vocabulary = &DefaultVocabulary();
  options.loop_closing = loop_closing;
  PlaceOutcome out;
  out.run = RunSlam(*dataset, options, run);
  out.gt = *dataset->ground_truth();
  const testing::TrajectoryScore score = testing::ScoreTrajectory(out.gt, out.run.trajectory);
  out.se3 = score.se3;
  out.sim3 = score.sim3;
  out.path_m = score.path_m;
  for (const FrameReport& r : out.run.reports) {
    out.lost += r.state == TrackingState::kLost;
    out.relocalized += r.relocalized;
    out.reinitialized += r.reinitialized;
  }
  for (const LoopClosure& l : out.run.loop_closures) {
    const double apart =
        (out.gt[l.frame_index].T_world_cam.translation() - out.gt[l.matched_frame_index].T_world_cam.translation())
            .norm();
    if (apart > 2.0) ++out.false_loops;
    std::printf("  loop frame %zu -> %zu (true centres %.2f m apart), %d points, scale %.4f, %.1f ms\n", l.frame_index,
                l.matched_frame_index, apart, l.matches, l.scale, l.correction_ms);
  }
  std::printf(
      "%s loops %s: %zu tracked, %zu lost, %zu relocalized, %zu reinit, %zu keyframes, %zu loops, ATE SE3 %.4f m "
      "(%.3f%% of %.1f m), Sim3 %.4f m\n",
      spec.c_str(), loop_closing ? "on" : "off", out.run.trajectory.size(), out.lost, out.relocalized,
      out.reinitialized, out.run.keyframe_count, out.run.loop_closures.size(), out.se3.ate_m.rmse,
      100 * out.se3.ate_m.rmse / out.path_m, out.path_m, out.sim3.ate_m.rmse);
  return out;
}

// First frame at which the camera is back within `radius` of where it was at frame 0, after
// having been farther than 2 * radius away.
size_t FirstReturn(const Trajectory& gt, double radius) {
  const Eigen::Vector3d start = gt.front().T_world_cam.translation();
  bool left = false;
  for (size_t i = 0; i < gt.size(); ++i) {
    const double d = (gt[i].T_world_cam.translation() - start).norm();
    if (d > 2 * radius) left = true;
    if (left && d < radius) return i;
  }
  return gt.size();
}

// The first revisit is closed, truly, within a few keyframes of the camera's return.
void ExpectTimelyTrueLoop(const PlaceOutcome& on) {
  ASSERT_FALSE(on.run.loop_closures.empty()) << "no loop detected";
  EXPECT_EQ(on.false_loops, 0);
  EXPECT_EQ(on.reinitialized, 0u);
  const size_t back = FirstReturn(on.gt, 0.5);
  const size_t closed = on.run.loop_closures.front().frame_index;
  size_t keyframes_between = 0;
  for (const FrameReport& r : on.run.reports) keyframes_between += r.keyframe && r.index >= back && r.index < closed;
  // Monocular tracking inserts keyframes several times as often, so a few seconds also count as
  // "few": 2.5 s (50 frames). Monocular maps triangulate only points with 2 degrees of parallax
  // (SlamOptions::min_parallax_deg), so the first keyframes of a revisit share fewer map points
  // with the first lap than they did at ORB-SLAM2's 1.15 degrees, and the geometric check passes
  // about 0.5 s later (frame 562 against 550 on this scene, 41 frames after the return).
  const size_t allowed_frames = 50;
  EXPECT_TRUE(keyframes_between <= 5 || closed - back <= allowed_frames)
      << "camera back at frame " << back << ", loop closed at frame " << closed << " after " << keyframes_between
      << " keyframes";
}

// Loop closing must remove at least two thirds of the drift of the same run without it.
void ExpectLoopClosureHelps(const std::string& spec, double max_path_fraction, bool sim3) {
  const PlaceOutcome off = RunScenario(spec, false);
  const PlaceOutcome on = RunScenario(spec, true);
  ExpectTimelyTrueLoop(on);
  const double ate_off = sim3 ? off.sim3.ate_m.rmse : off.se3.ate_m.rmse;
  const double ate_on = sim3 ? on.sim3.ate_m.rmse : on.se3.ate_m.rmse;
  EXPECT_LT(ate_on, ate_off / 3) << "loop closing should remove most of the drift";
  EXPECT_LT(ate_on, max_path_fraction * on.path_m);
}

// bench/place_bench.sh runs the 60 s versions of all three sensors with and without loops.
TEST(LoopClosing, StereoRoom) {
  ExpectLoopClosureHelps("synth:room:duration=60,width=480,height=360", 0.005, false);
}

TEST(LoopClosing, MonocularRoom) {
  ExpectLoopClosureHelps("synth:room:duration=40,width=480,height=360,sensor=mono", 0.02, true);
}

TEST(LoopClosing, RgbdRoom) {
  const PlaceOutcome on = RunScenario("synth:room:duration=40,width=480,height=360,sensor=rgbd", true);
  ExpectTimelyTrueLoop(on);
  EXPECT_LT(on.se3.ate_m.rmse, 0.005 * on.path_m);
}

TEST(Relocalization, KidnappedStereoRoomResumesInTheSameMap) {
  // The camera jumps: 60 frames (3 s) are never seen; it lands in a part of the room mapped on
  // the first lap (a lap takes about 26 s), so it must relocalize rather than start anew.
  SlamRunOptions run;
  run.skip = {{600, 660}};
  const PlaceOutcome o = RunScenario("synth:room:duration=40,width=480,height=360", false, run);
  EXPECT_EQ(o.reinitialized, 0u) << "a new map segment means relocalization failed";
  EXPECT_GE(o.relocalized, 1u);
  size_t first_ok_after = 0;
  for (const FrameReport& r : o.run.reports)
    if (r.index >= 660 && r.state == TrackingState::kOk) {
      first_ok_after = r.index;
      break;
    }
  EXPECT_GE(first_ok_after, 660u);
  EXPECT_LT(first_ok_after, 670u) << "relocalized within 10 frames";
  EXPECT_LT(o.se3.ate_m.rmse, 0.01 * o.path_m);  // one map, one frame: the trajectory stays consistent
}

TEST(Relocalization, KittiMonocularForcedLossAndNoFalseLoop) {
  const auto seq = testing::DatasetsDir() / "kitti" / "sequences" / "07";
  SlamRunOptions run;
  run.lose_at = {80};
  const auto dataset = OpenDataset(seq.string());
  SlamOptions options;
  options.orb.features = 2000;
  options.vocabulary = &DefaultVocabulary();
  const SlamRunResult r = RunSlam(*dataset, options, run);
  EXPECT_TRUE(r.loop_closures.empty()) << "the snippet has no loop";
  size_t resumed = 0, reinitialized = 0;
  for (const FrameReport& f : r.reports) {
    reinitialized += f.reinitialized;
    if (f.index >= 80 && f.state == TrackingState::kOk && resumed == 0) resumed = f.index;
  }
  EXPECT_EQ(reinitialized, 0u);
  EXPECT_GE(resumed, 80u);
  EXPECT_LT(resumed, 90u) << "relocalized within 10 frames of the loss";
  EXPECT_GE(r.trajectory.size(), r.reports.size() - 20);
}

}  // namespace
}  // namespace flatslam
