// End-to-end SLAM runs on synthetic scenes (exact ground truth) and the real KITTI snippets, with
// the options `flatslam run` uses (the shipped vocabulary included). Thresholds are the issue's
// bars; docs/STATUS.md gives the measured figures.
#include "jobs/slam_runner.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <initializer_list>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgproc.hpp>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "io/orb_settings.h"
#include "place/vocabulary.h"
#include "default_vocabulary.h"
#include "test_data.h"
#include "trajectory_score.h"
#include "trajectory/metrics.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

struct RunOutcome {
  SlamRunResult run;
  EvalResult se3;
  EvalResult sim3;
  double path_m = 0;
  size_t lost = 0;
};

// features 0: the budget derived from the camera, as `flatslam run` does by default.
RunOutcome RunAndScore(const std::string& spec, bool deterministic, int features = 1000,
                    std::optional<Sensor> sensor = std::nullopt, bool check_camera = false) {
  DatasetOptions dataset_options;
  dataset_options.sensor = sensor;
  const auto dataset = OpenDataset(spec, dataset_options);
  SlamOptions options = testing::OptionsWithDefaultVocabulary();
  options.orb.features = features;
  SlamRunOptions run;
  run.deterministic = deterministic;
  run.check_camera = check_camera;
  RunOutcome out;
  out.run = RunSlam(*dataset, options, run);
  const testing::TrajectoryScore score = testing::ScoreTrajectory(*dataset->ground_truth(), out.run.trajectory);
  out.se3 = score.se3;
  out.sim3 = score.sim3;
  out.path_m = score.path_m;
  for (const FrameReport& r : out.run.reports) out.lost += r.state != TrackingState::kOk;
  std::printf("%s: %zu frames, %zu lost, %zu keyframes, %zu points, ATE %.4f m (%.3f%% of %.1f m), scale %.4f\n",
              spec.c_str(), out.run.trajectory.size(), out.lost, out.run.keyframe_count, out.run.point_count,
              out.se3.ate_m.rmse, 100 * out.se3.ate_m.rmse / out.path_m, out.path_m, out.sim3.alignment.scale);
  return out;
}

// The index of the first frame that tracking gave a pose (the end of the start).
size_t FirstTracked(const SlamRunResult& run) {
  size_t first = run.reports.size();
  for (const FrameReport& r : run.reports)
    if (r.state == TrackingState::kOk) first = std::min(first, r.index);
  return first;
}

TEST(SlamRun, StereoRoomTracksEveryFrameBelowOnePercent) {
  const RunOutcome o = RunAndScore("synth:room:duration=15,width=480,height=360", false);
  EXPECT_EQ(o.run.trajectory.size(), o.run.reports.size());
  EXPECT_EQ(o.lost, 0u);
  EXPECT_LT(o.se3.ate_m.rmse, 0.01 * o.path_m);
  EXPECT_NEAR(o.sim3.alignment.scale, 1.0, 0.01);
  EXPECT_GT(o.run.keyframe_count, 3u);
}

TEST(SlamRun, RgbdRoomTracksEveryFrameBelowOnePercent) {
  const RunOutcome o = RunAndScore("synth:room:duration=15,width=480,height=360,sensor=rgbd", false);
  EXPECT_EQ(o.lost, 0u);
  EXPECT_LT(o.se3.ate_m.rmse, 0.01 * o.path_m);
}

TEST(SlamRun, DeterministicModeRepeatsExactly) {
  const RunOutcome a = RunAndScore("synth:corridor:duration=4,width=480,height=360", true);
  const RunOutcome b = RunAndScore("synth:corridor:duration=4,width=480,height=360", true);
  ASSERT_EQ(a.run.trajectory.size(), b.run.trajectory.size());
  for (size_t i = 0; i < a.run.trajectory.size(); ++i)
    ASSERT_TRUE(a.run.trajectory[i].T_world_cam.isApprox(b.run.trajectory[i].T_world_cam, 0.0)) << "frame " << i;
  EXPECT_EQ(a.run.point_count, b.run.point_count);
}

// Without mapping lag a run maps each keyframe in its track stage, and the kernels that split
// their work over the cores (extraction, stereo matching, triangulation a neighbour per task) give
// the same result whatever the threads: with no loop to close, a default run repeats the
// deterministic run exactly, on two threads and on one.
TEST(SlamRun, WithoutLagADefaultRunRepeatsTheDeterministicRunOnAnyThreads) {
  const std::string spec = "synth:corridor:duration=4,width=480,height=360";
  const RunOutcome reference = RunAndScore(spec, true);
  const RunOutcome fast = RunAndScore(spec, false);
  RunOutcome single;
  tbb::task_arena one_thread(1);
  one_thread.execute([&] { single = RunAndScore(spec, false); });
  for (const RunOutcome* o : std::initializer_list<const RunOutcome*>{&fast, &single}) {
    EXPECT_TRUE(o->run.loop_closures.empty());
    ASSERT_EQ(o->run.trajectory.size(), reference.run.trajectory.size());
    for (size_t i = 0; i < o->run.trajectory.size(); ++i)
      ASSERT_TRUE(o->run.trajectory[i].T_world_cam.isApprox(reference.run.trajectory[i].T_world_cam, 0.0))
          << "frame " << i;
    EXPECT_EQ(o->run.point_count, reference.run.point_count);
  }
}

// Deterministic runs map inline, on the track stage, and run global bundle adjustment inline
// after a loop: the adjustment must take the map lock only after loop correction released it
// (it once waited on itself forever). A lap of the room takes about 26 s.
TEST(SlamRun, DeterministicRunClosesALoopAndFinishes) {
  const RunOutcome o = RunAndScore("synth:room:duration=32,width=480,height=360,sensor=rgbd", true);
  EXPECT_GE(o.run.loop_closures.size(), 1u);
  EXPECT_EQ(o.run.trajectory.size(), o.run.reports.size());
  EXPECT_LT(o.se3.ate_m.rmse, 0.005 * o.path_m);
}

// A map server's correction moves an agent's map into the merged map's frame mid-run
// (SlamSession::MoveMapFrame, from the mapping lane): every pose after the move, and the refined
// trajectory of the whole run, come out in the new frame, as the same run's poses moved by the
// transform; frames report which frame their pose is in; nothing is lost. A monocular map moves
// with a scale (the merged map's): its frames' poses relative to keyframes, recorded before the
// move, scale with it.
// two_steps: the same move made as two, a keyframe apart (frames tracked between them are in
// neither frame and are skipped).
void MoveTheMapFrameMidRun(const std::string& spec, double scale, size_t at_keyframe, bool two_steps = false) {
  const auto dataset = OpenDataset(spec);
  SlamOptions options = testing::OptionsWithDefaultVocabulary();
  Eigen::Isometry3d T_new_old = Eigen::Isometry3d::Identity();
  T_new_old.linear() = Eigen::AngleAxisd(0.5, Eigen::Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  T_new_old.translation() = Eigen::Vector3d(3, -1, 2);
  // A camera pose (T_world_cam) moved: centre by X_new = scale * R X + t, orientation by R.
  auto moved_pose = [&](const Eigen::Isometry3d& T_world_cam) {
    Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
    out.linear() = T_new_old.linear() * T_world_cam.linear();
    out.translation() = scale * (T_new_old.linear() * T_world_cam.translation()) + T_new_old.translation();
    return out;
  };
  // A checkpoint taken after the move holds every frame anchored in the moved map, as the
  // session's own trajectory has it (frames recorded before the move among them).
  double worst_checkpoint = -1;
  auto check_checkpoint = [&](SlamSession& slam) {
    SlamSession::State state;
    slam.CaptureState(&state);
    std::vector<AnchoredFramePose> frames;
    state.AnchoredToMap(&frames);
    const Trajectory trajectory = slam.FrameTrajectory();
    EXPECT_EQ(frames.size(), trajectory.size());
    worst_checkpoint = 0;
    for (size_t i = 0; i < frames.size() && i < trajectory.size(); ++i) {
      const AnchoredFramePose& f = frames[i];
      const Eigen::Isometry3d T_cam_world = f.reference.is_null()
                                                ? f.T_cam_world.isometry()
                                                : f.T_cam_ref.isometry() * state.map.keyframe(f.reference).T_cam_world;
      worst_checkpoint = std::max(
          worst_checkpoint, (T_cam_world.inverse().translation() - trajectory[i].T_world_cam.translation()).norm());
    }
  };
  auto run_once = [&](bool move) {
    SlamRunOptions run;
    run.deterministic = true;
    size_t keyframes = 0;
    run.on_keyframe_mapped = [&](SlamSession& slam, KeyFrameHandle) {
      if (!move) return;
      ++keyframes;
      if (keyframes == at_keyframe + 4) check_checkpoint(slam);
      if (!two_steps) {
        if (keyframes == at_keyframe) slam.MoveMapFrame(T_new_old, scale);
        return;
      }
      // First X1 = s1 X + t1, then what remains: X_new = s2 R X1 + t2 with s1 s2 = scale and
      // s2 R t1 + t2 = t.
      const double s1 = std::sqrt(scale), s2 = scale / s1;
      const Eigen::Vector3d t1(1, 0.5, -2);
      if (keyframes == at_keyframe) {
        Eigen::Isometry3d T1 = Eigen::Isometry3d::Identity();
        T1.translation() = t1;
        slam.MoveMapFrame(T1, s1);
      } else if (keyframes == at_keyframe + 1) {
        Eigen::Isometry3d T2 = T_new_old;
        T2.translation() = T_new_old.translation() - s2 * (T_new_old.linear() * t1);
        slam.MoveMapFrame(T2, s2);
      }
    };
    return RunSlam(*dataset, options, run);
  };
  const SlamRunResult plain = run_once(false), moved = run_once(true);
  ASSERT_EQ(moved.reports.size(), plain.reports.size());
  // Up to the move the runs are the same; the first frames after it are the plain run's poses
  // moved, to rounding. Later the two runs part by rounding (a different RANSAC sample or keyframe
  // decision), as any two runs of different numbers do, so they are compared with the ground truth.
  size_t before = 0, after = 0, lost = 0;
  double worst_before = 0, worst_first_after = 0;
  for (size_t i = 0; i < moved.reports.size(); ++i) {
    const FrameReport& r = moved.reports[i];
    lost += r.state != TrackingState::kOk && r.state != TrackingState::kNotInitialized;
    if (!r.T_world_cam || !plain.reports[i].T_world_cam) continue;
    const uint32_t last_frame = two_steps ? 2 : 1;
    ASSERT_LE(r.map_frame, last_frame);
    if (r.map_frame != 0 && r.map_frame != last_frame) continue;
    const Eigen::Isometry3d expected =
        r.map_frame == 0 ? *plain.reports[i].T_world_cam : moved_pose(*plain.reports[i].T_world_cam);
    const double d = (expected.translation() - r.T_world_cam->translation()).norm();
    if (r.map_frame == 0) {
      ++before;
      worst_before = std::max(worst_before, d);
    } else if (++after <= 10) {
      worst_first_after = std::max(worst_first_after, d);
    }
  }
  std::printf(
      "%zu frames tracked before the move, %zu after; the first 10 after it %.1g m from the plain run's "
      "moved\n",
      before, after, worst_first_after);
  std::printf("checkpoint after the move: its frames %.1g from the session's trajectory\n", worst_checkpoint);
  EXPECT_GE(worst_checkpoint, 0.0);           // taken
  EXPECT_LT(worst_checkpoint, 1e-5 * scale);  // single-precision records
  EXPECT_EQ(lost, 0u);
  EXPECT_GT(before, 10u);
  EXPECT_GT(after, 50u);
  EXPECT_EQ(worst_before, 0.0);
  // A stereo run goes on as the plain one moved, to rounding. A monocular one parts from it within
  // a few frames even when moved rigidly (its triangulations pass or fail thresholds by rounding),
  // so its first frames after the move agree to millimetres.
  EXPECT_LT(worst_first_after, spec.find("sensor=mono") != std::string::npos ? 0.005 * scale : 1e-4);
  // The refined trajectory of the whole run is in the new frame: against the plain run's, moved,
  // and with the ground truth after alignment.
  ASSERT_EQ(moved.trajectory.size(), plain.trajectory.size());
  EXPECT_LT((moved.trajectory.front().T_world_cam.translation() -
             moved_pose(plain.trajectory.front().T_world_cam).translation())
                .norm(),
            0.01 * scale);
  const testing::TrajectoryScore a = testing::ScoreTrajectory(*dataset->ground_truth(), plain.trajectory);
  const testing::TrajectoryScore b = testing::ScoreTrajectory(*dataset->ground_truth(), moved.trajectory);
  if (scale == 1.0) {
    std::printf("ATE plain %.4f m, moved %.4f m over %.1f m\n", a.se3.ate_m.rmse, b.se3.ate_m.rmse, b.path_m);
    EXPECT_LT(b.se3.ate_m.rmse, 0.01 * b.path_m);
    // The alignment to the ground truth is the move's: the moved run's world is T_new_old's.
    const Eigen::Isometry3d plain_to_gt = a.se3.alignment.Apply(Eigen::Isometry3d::Identity());
    const Eigen::Isometry3d old_to_gt = b.se3.alignment.Apply(T_new_old);  // x -> A_moved(T_new_old x)
    EXPECT_LT((old_to_gt.translation() - plain_to_gt.translation()).norm(), 0.05);
    EXPECT_LT(Eigen::AngleAxisd(old_to_gt.linear().transpose() * plain_to_gt.linear()).angle(), 0.01);
  } else {
    // Every frame, those recorded before the move among them, carries the new scale: the
    // similarity to the ground truth shrinks by it, and the shape stays as good.
    std::printf("Sim(3) ATE plain %.4f m (scale %.4f), moved %.4f m (scale %.4f) over %.1f m\n", a.sim3.ate_m.rmse,
                a.sim3.alignment.scale, b.sim3.ate_m.rmse, b.sim3.alignment.scale, b.path_m);
    EXPECT_LT(b.sim3.ate_m.rmse, 0.01 * b.path_m);
    EXPECT_NEAR(b.sim3.alignment.scale * scale / a.sim3.alignment.scale, 1.0, 0.02);
    // Frames recorded before the move are as far from their keyframes, scaled: the first second of
    // the refined trajectory, moved back, is the plain run's.
    double worst_early = 0;
    for (size_t i = 0; i < 10 && i < moved.trajectory.size(); ++i)
      worst_early = std::max(worst_early, (moved.trajectory[i].T_world_cam.translation() -
                                           moved_pose(plain.trajectory[i].T_world_cam).translation())
                                              .norm());
    EXPECT_LT(worst_early, 0.01 * scale);
  }
}

TEST(SlamRun, MovingTheMapFrameMidRunMovesEveryPose) {
  MoveTheMapFrameMidRun("synth:room:duration=8,width=480,height=360", 1.0, 5);
}

TEST(SlamRun, MovingAMonocularMapFrameWithAScaleScalesEveryPose) {
  MoveTheMapFrameMidRun("synth:room:duration=8,width=480,height=360,sensor=mono", 1.7, 12);
}

TEST(SlamRun, TwoMovesOfAMonocularMapComposeAsOne) {
  MoveTheMapFrameMidRun("synth:room:duration=8,width=480,height=360,sensor=mono", 1.7, 12, /*two_steps=*/true);
}

// A stereo or RGB-D map's depths are metric: it moves rigidly or not at all.
TEST(SlamSession, OnlyAMonocularMapMovesWithAScale) {
  const auto dataset = OpenDataset("synth:room:duration=1,width=480,height=360");
  const SlamOptions options;
  SlamSession session(dataset->calibration(), options);
  try {
    session.MoveMapFrame(Eigen::Isometry3d::Identity(), 2.0);
    FAIL() << "a stereo map moved with a scale";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("metric"), std::string::npos) << e.what();
  }
  EXPECT_THROW(session.MoveMapFrame(Eigen::Isometry3d::Identity(), 0.0), Error);
  session.MoveMapFrame(Eigen::Isometry3d::Identity(), 1.0);
}

// A dataset seen through a refined camera passes its images as given, each frame with the lens;
// the session moves the keypoints measured in them into the refined camera, where they land on
// the keypoints of the image undistorted pixel by pixel (the same corners, within resampling).
TEST(SlamSession, KeypointsOfAGivenImageMoveThroughTheFramesLens) {
  DatasetOptions mono;
  mono.sensor = Sensor::kMonocular;
  const std::string scene = "synth:room:duration=0.5,width=480,height=360,k1=0.03";
  const auto given = OpenDataset(scene, mono);
  const CameraRefit refit{1.004, 0.03};
  const auto refined = ApplyCameraRefit(OpenDataset(scene, mono), refit);
  const Frame raw = given->read(3), frame = refined->read(3);
  ASSERT_TRUE(frame.lens);
  EXPECT_FALSE(raw.lens);
  EXPECT_EQ(cv::norm(raw.left, frame.left, cv::NORM_INF), 0);  // no pixel resampled
  const PinholeCamera& cam = refined->calibration().camera;

  SlamOptions options;
  options.orb.features = 1000;
  SlamSession session(refined->calibration(), options);
  TrackedFrame through_lens, of_given, of_undistorted;
  session.Extract(frame, &through_lens);
  session.Extract(raw, &of_given);
  // The same image undistorted pixel by pixel into the refined camera.
  const PinholeCamera& g = given->calibration().camera;
  const cv::Matx33d lens(g.fx * refit.focal_scale, 0, g.cx, 0, g.fy * refit.focal_scale, g.cy, 0, 0, 1);
  const cv::Matx33d undistorted(cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1);
  cv::Mat map_u, map_v, image;
  cv::initUndistortRectifyMap(lens, cv::Mat(cv::Vec4d(refit.k1, 0, 0, 0)), cv::Mat::eye(3, 3, CV_64F), undistorted,
                              raw.left.size(), CV_32FC1, map_u, map_v);
  cv::remap(raw.left, image, map_u, map_v, cv::INTER_LINEAR);
  Frame resampled = raw;
  resampled.left = image;
  session.Extract(resampled, &of_undistorted);

  const Keypoints& k = through_lens.keypoints;
  ASSERT_GT(k.size(), 500u);
  EXPECT_TRUE(k.consistent());
  EXPECT_LE(k.size(), of_given.keypoints.size());  // those beyond the refined image are dropped
  EXPECT_EQ(through_lens.points.size(), k.size());
  const RefinedCamera refined_camera(g, refit);
  size_t moved = 0, near = 0;
  for (size_t i = 0; i < k.size(); ++i) {
    EXPECT_TRUE(k.uv[i].x() >= 0 && k.uv[i].y() >= 0 && k.uv[i].x() <= cam.width - 1 && k.uv[i].y() <= cam.height - 1);
    // Each is a keypoint of the given image, moved by the lens.
    const Eigen::Vector2d back = refined_camera.ToGiven(std::vector{Eigen::Vector2d(k.uv[i].cast<double>())})[0];
    bool found = false;
    for (size_t j = 0; j < of_given.keypoints.size() && !found; ++j)
      found = (of_given.keypoints.uv[j].cast<double>() - back).norm() < 1e-3 &&
              of_given.keypoints.descriptor[j] == k.descriptor[i];
    EXPECT_TRUE(found) << i;
    if ((k.uv[i].cast<double>() - back).norm() > 0.5) ++moved;
    for (const Eigen::Vector2f& q : of_undistorted.keypoints.uv)
      if ((q - k.uv[i]).norm() < 1.5f) {
        ++near;
        break;
      }
  }
  EXPECT_GT(moved, k.size() / 2) << moved << " of " << k.size();  // most move by over half a pixel
  EXPECT_GT(near, k.size() * 6 / 10) << near << " of " << k.size();  // onto the undistorted image's corners

  // Only a monocular image is undistorted keypoint by keypoint.
  const auto stereo = OpenDataset("synth:room:duration=0.5,width=480,height=360");
  SlamSession stereo_session(stereo->calibration(), options);
  Frame stereo_frame = stereo->read(0);
  stereo_frame.lens = frame.lens;
  TrackedFrame out;
  EXPECT_THROW(stereo_session.Extract(stereo_frame, &out), Error);
}

// Several sessions live in one process (nothing static): two runs on different scenes at the same
// time each give exactly the trajectory they give alone.
TEST(SlamRun, ConcurrentSessionsMatchTheirSingleRuns) {
  const std::string specs[2] = {"synth:corridor:duration=4,width=480,height=360",
                                "synth:room:duration=4,width=480,height=360,sensor=rgbd"};
  RunOutcome alone[2], together[2];
  for (int k = 0; k < 2; ++k) alone[k] = RunAndScore(specs[k], true);
  std::thread other([&] { together[1] = RunAndScore(specs[1], true); });
  together[0] = RunAndScore(specs[0], true);
  other.join();
  for (int k = 0; k < 2; ++k) {
    SCOPED_TRACE(specs[k]);
    ASSERT_EQ(together[k].run.trajectory.size(), alone[k].run.trajectory.size());
    ASSERT_GT(alone[k].run.trajectory.size(), 50u);
    for (size_t i = 0; i < alone[k].run.trajectory.size(); ++i)
      ASSERT_TRUE(together[k].run.trajectory[i].T_world_cam.isApprox(alone[k].run.trajectory[i].T_world_cam, 0.0))
          << "frame " << i;
    EXPECT_EQ(together[k].run.point_count, alone[k].run.point_count);
  }
}

TEST(SlamRun, KittiStereoSnippet) {
  const auto seq = testing::DatasetsDir() / "kitti" / "sequences" / "06";
  const RunOutcome o = RunAndScore(seq.string(), false, 0);
  EXPECT_EQ(o.lost, 0u);
  EXPECT_EQ(o.run.trajectory.size(), 51u);
  // Bar: ORB-SLAM2's 0.059 m after SE(3); scale within 1%.
  EXPECT_LT(o.se3.ate_m.rmse, 0.059);
  EXPECT_NEAR(o.sim3.alignment.scale, 1.0, 0.01);
}

// Every stride-th frame of a KITTI sequence as a sequence of its own (symlinks, times and poses
// kept): the same camera driving stride times as fast, at 10 / stride Hz.
std::filesystem::path KittiEveryNthFrame(const std::string& sequence, int stride) {
  namespace fs = std::filesystem;
  const fs::path kitti = testing::DatasetsDir() / "kitti";
  const fs::path source = kitti / "sequences" / sequence;
  const fs::path root = testing::FreshTempDir("kitti_stride" + std::to_string(stride));
  const fs::path target = root / "sequences" / sequence;
  fs::create_directories(root / "poses");
  fs::copy_file(source / "calib.txt", (fs::create_directories(target), target / "calib.txt"));
  std::ifstream times_in(source / "times.txt"), poses_in(kitti / "poses" / (sequence + ".txt"));
  std::ofstream times_out(target / "times.txt"), poses_out(root / "poses" / (sequence + ".txt"));
  std::string time, pose;
  for (int i = 0, k = 0; std::getline(times_in, time) && std::getline(poses_in, pose); ++i) {
    if (i % stride != 0) continue;
    char from[16], to[16];
    std::snprintf(from, sizeof(from), "%06d.png", i);
    std::snprintf(to, sizeof(to), "%06d.png", k++);
    for (const char* camera : {"image_0", "image_1"}) {
      if (!fs::exists(source / camera / from)) continue;
      fs::create_directories(target / camera);
      fs::create_symlink(source / camera / from, target / camera / to);
    }
    times_out << time << "\n";
    poses_out << pose << "\n";
  }
  return target;
}

// Fast motion with real images: the stereo snippet at 2x and 3x its speed (2.4 and 3.6 m a
// frame). Tracking without a motion prior used to search only around the last pose, found
// mostly far points there and kept a pose with a tenth of the motion (ATE 10.7 and 14.5 m, scale
// 2.0 and 5.7). Bar: the for the synthetic highway, under 0.5% of the path, scale
// within 1%.
TEST(SlamRun, KittiStereoAtTwiceAndThreeTimesTheSpeed) {
  for (int stride : {2, 3}) {
    const RunOutcome o = RunAndScore(KittiEveryNthFrame("06", stride).string(), false, 0);
    EXPECT_EQ(o.lost, 0u) << "stride " << stride;
    EXPECT_EQ(o.run.trajectory.size(), static_cast<size_t>((51 + stride - 1) / stride)) << "stride " << stride;
    EXPECT_LT(o.se3.ate_m.rmse, 0.005 * o.path_m) << "stride " << stride;
    EXPECT_NEAR(o.sim3.alignment.scale, 1.0, 0.01) << "stride " << stride;
  }
}

// Dropped frames on a fast-moving car: KITTI 06 stereo (1.2 m a frame) with 7 of its 51 frames
// missing in gaps of 1-3. The motion prediction used to replay the last step as it was, half or
// a third of the motion since the last frame after a gap; tracking settled on far points around
// that pose and the error carried on (ATE 1.16 m, scale 1.054). It now continues the velocity
// for the frame periods that passed. Bar: the snippet's own, 0.059 m, 0 lost. KITTI 07
// monocular with 7 frames dropped: Sim(3) 0.463 m before, 0.303 m now; bar 0.5% of the path (as
// for half the frame rate), 0 lost.
TEST(SlamRun, DroppedFramesOnAFastCar) {
  SlamOptions options = testing::OptionsWithDefaultVocabulary();
  struct Case {
    const char* sequence;
    Sensor sensor;
    std::vector<std::pair<size_t, size_t>> skip;
  };
  for (const Case& c : {Case{"06", Sensor::kStereo, {{10, 11}, {20, 22}, {30, 31}, {40, 43}}},
                        Case{"07", Sensor::kMonocular, {{30, 31}, {60, 62}, {90, 91}, {120, 123}}}}) {
    DatasetOptions dataset_options;
    dataset_options.sensor = c.sensor;
    const auto dataset =
        OpenDataset((testing::DatasetsDir() / "kitti" / "sequences" / c.sequence).string(), dataset_options);
    SlamRunOptions run;
    run.skip = c.skip;
    const SlamRunResult result = RunSlam(*dataset, options, run);
    const testing::TrajectoryScore score = testing::ScoreTrajectory(*dataset->ground_truth(), result.trajectory);
    const auto lost = std::count_if(result.reports.begin(), result.reports.end(),
                                    [](const FrameReport& r) { return r.state == TrackingState::kLost; });
    EXPECT_EQ(lost, 0) << c.sequence;
    if (c.sensor == Sensor::kStereo) {
      EXPECT_EQ(result.trajectory.size(), 44u);
      EXPECT_LT(score.se3.ate_m.rmse, 0.059);
      EXPECT_NEAR(score.sim3.alignment.scale, 1.0, 0.01);
    } else {
      EXPECT_LT(score.sim3.ate_m.rmse, 0.005 * score.path_m);
    }
  }
}

// Monocular KITTI at half its frame rate (every 2nd frame: 4.8 Hz, 1.1 m a frame on 07, 2.4 m
// on 06). With keyframes at least 2 frames (0.4 s) apart the map ran out of points on 07's
// straight and 06's start: 11 frames lost on each, a new segment, Sim(3) ATE 11.2 m and 17.3 m.
// The monocular spacing now follows the frame rate (1 frame below 7.5 Hz). Bar: no frame lost
// after initialization, Sim(3) ATE under 0.5% of the path (the synthetic highway's bar).
TEST(SlamRun, KittiMonocularAtHalfTheFrameRate) {
  for (const char* sequence : {"07", "06"}) {
    const RunOutcome o = RunAndScore(KittiEveryNthFrame(sequence, 2).string(), false, 0, Sensor::kMonocular);
    const auto lost = std::count_if(o.run.reports.begin(), o.run.reports.end(),
                                    [](const FrameReport& r) { return r.state == TrackingState::kLost; });
    EXPECT_EQ(lost, 0) << sequence;
    EXPECT_LT(o.sim3.ate_m.rmse, 0.005 * o.path_m) << sequence;
  }
}

// Every stride-th frame of the EuRoC MH_01 snippet as a dataset of its own (images linked, ground
// truth kept): the same hand-held shaking at 20 / stride Hz.
std::filesystem::path EurocEveryNthFrame(int stride) {
  namespace fs = std::filesystem;
  const fs::path source = testing::DatasetsDir() / "euroc" / "MH_01_f000_149";
  const fs::path root = testing::FreshTempDir("euroc_stride" + std::to_string(stride));
  fs::copy_file(source / "groundtruth_tum.txt", root / "groundtruth_tum.txt");
  for (const char* camera : {"cam0", "cam1"}) {
    const fs::path from = source / "mav0" / camera, to = root / "mav0" / camera;
    fs::create_directories(to);
    fs::copy_file(from / "sensor.yaml", to / "sensor.yaml");
    fs::create_directory_symlink(from / "data", to / "data");
    std::ifstream in(from / "data.csv");
    std::ofstream out(to / "data.csv");
    std::string line;
    for (int i = -1; std::getline(in, line); ++i)
      if (i < 0 || i % stride == 0) out << line << "\n";  // the header, then every stride-th image
  }
  return root;
}

// Hand-held stereo at a quarter of the frame rate: the constant-velocity prediction lands 10-45
// pixels from the tracked pose, and the fixed 7-pixel motion search found a sliver of the points
// (two frames kept 53 and 59 inliers and lost 3 cm each; ATE 0.0515 m, 2.6% of the path). The
// window now follows the measured prediction error. Bar: the for hand-held stereo, no
// frame lost and ATE under 1% of the path, at every rate.
TEST(SlamRun, EurocHandheldStereoAtAHalfAndAQuarterOfTheFrameRate) {
  for (int stride : {2, 4}) {
    const RunOutcome o = RunAndScore(EurocEveryNthFrame(stride).string(), false, 0, Sensor::kStereo);
    EXPECT_EQ(o.lost, 0u) << "stride " << stride;
    EXPECT_EQ(o.run.trajectory.size(), static_cast<size_t>((150 + stride - 1) / stride)) << "stride " << stride;
    EXPECT_LT(o.se3.ate_m.rmse, 0.01 * o.path_m) << "stride " << stride;
  }
}

// Copies calib.txt from `source` to `target`, passing each line's 12 numbers (a 3x4 projection
// matrix, row-major) through edit(name, numbers) on the way.
void RewriteKittiCalibration(const std::filesystem::path& source, const std::filesystem::path& target,
                             const std::function<void(const std::string& name, double* v)>& edit) {
  std::ifstream in(source / "calib.txt");
  std::ofstream out(target / "calib.txt");
  out.precision(12);
  for (std::string line; std::getline(in, line);) {
    std::istringstream fields(line);
    std::string name;
    fields >> name;
    double v[12];
    for (double& x : v) fields >> x;
    edit(name, v);
    out << name;
    for (double x : v) out << " " << x;
    out << "\n";
  }
}

// A KITTI sequence with every image scaled by `factor` (area-averaged) and the projection
// matrices scaled to match (pixel centres kept): the same scene seen by a smaller camera.
std::filesystem::path KittiResized(const std::string& sequence, double factor) {
  namespace fs = std::filesystem;
  const fs::path kitti = testing::DatasetsDir() / "kitti";
  const fs::path source = kitti / "sequences" / sequence;
  const fs::path root = testing::FreshTempDir("kitti_resized" + std::to_string(static_cast<int>(100 * factor)));
  const fs::path target = root / "sequences" / sequence;
  fs::create_directories(root / "poses");
  fs::copy_file(kitti / "poses" / (sequence + ".txt"), root / "poses" / (sequence + ".txt"));
  fs::create_directories(target);
  fs::copy_file(source / "times.txt", target / "times.txt");
  for (const char* camera : {"image_0", "image_1"}) {
    if (!fs::exists(source / camera)) continue;
    fs::create_directories(target / camera);
    for (const fs::directory_entry& e : fs::directory_iterator(source / camera)) {
      cv::Mat image = cv::imread(e.path().string(), cv::IMREAD_UNCHANGED), scaled;
      cv::resize(image, scaled, cv::Size(), factor, factor, cv::INTER_AREA);
      cv::imwrite((target / camera / e.path().filename()).string(), scaled);
    }
  }
  // P = K [I | t]: rows 0 and 1 scale (focal lengths, fx * baseline), principal points move
  // with the pixel centres.
  RewriteKittiCalibration(source, target, [&](const std::string&, double* v) {
    for (int k = 0; k < 4; ++k) {
      v[k] *= factor;
      v[4 + k] *= factor;
    }
    v[2] += 0.5 * factor - 0.5;  // c' = (c + 0.5) f - 0.5, with P[0][2], P[1][2] = cx, cy (P[2][2] = 1)
    v[6] += 0.5 * factor - 0.5;
  });
  return target;
}

// The stereo snippet seen by a camera of three quarters and half the size (920x277, 613x185), and
// monocular at three quarters. The feature budget follows the camera's linear size (1500, 1000);
// one following its area (1200, 500) lost 7 monocular frames at three quarters (Sim(3) 0.08 m)
// and doubled the stereo error at half size. Monocular at half size still loses frames with the
// derived 1000 (docs/STATUS.md). Bars: the for monocular scenes (no frame lost after the
// start, Sim(3) ATE under 2% of the path) and for stereo (under 0.5% of the path, scale within 1%).
TEST(SlamRun, KittiAtThreeQuartersAndHalfTheResolution) {
  for (double factor : {0.75, 0.5}) {
    const std::string seq = KittiResized("06", factor).string();
    const RunOutcome stereo = RunAndScore(seq, false, 0);
    EXPECT_EQ(stereo.lost, 0u) << factor;
    EXPECT_LT(stereo.se3.ate_m.rmse, 0.005 * stereo.path_m) << factor;
    EXPECT_NEAR(stereo.sim3.alignment.scale, 1.0, 0.01) << factor;
    if (factor < 0.75) continue;
    const RunOutcome mono = RunAndScore(seq, false, 0, Sensor::kMonocular);
    const size_t first_tracked = FirstTracked(mono.run);
    EXPECT_LE(first_tracked, 5u) << factor;
    EXPECT_EQ(mono.run.trajectory.size(), mono.run.reports.size() - first_tracked) << factor;
    EXPECT_LT(mono.sim3.ate_m.rmse, 0.02 * mono.path_m) << factor;
  }
}

// A KITTI sequence played backward (`reverse`: image k is image n-1-k, its pose with it, times
// kept) and/or seen in a mirror (`mirror`: every image flipped left to right, the world's x
// negated). A mirrored stereo pair swaps its cameras: the flipped right image is the left image
// of the mirrored world, whose camera sits one baseline to the left of the original left camera.
// The same real images and calibration, driving motions the snippets do not have: backward, and
// turning the other way.
std::filesystem::path KittiReversedOrMirrored(const std::string& sequence, bool reverse, bool mirror) {
  namespace fs = std::filesystem;
  const fs::path kitti = testing::DatasetsDir() / "kitti";
  const fs::path source = kitti / "sequences" / sequence;
  const fs::path root =
      testing::FreshTempDir("kitti_" + sequence + (reverse ? "_reversed" : "") + (mirror ? "_mirrored" : ""));
  const fs::path target = root / "sequences" / sequence;
  fs::create_directories(target);
  fs::create_directories(root / "poses");
  const bool stereo = fs::exists(source / "image_1");
  std::vector<std::string> times;
  {
    std::ifstream times_in(source / "times.txt");
    for (std::string line; std::getline(times_in, line);) times.push_back(line);
  }
  const Trajectory poses = ReadKitti(kitti / "poses" / (sequence + ".txt"));
  const size_t n = std::min(times.size(), poses.size());
  const int width = cv::imread((source / "image_0" / "000000.png").string(), cv::IMREAD_UNCHANGED).cols;

  // calib.txt: a mirror moves each principal point to width - 1 - cx; P1 keeps its -fx * baseline.
  double baseline_m = 0;
  RewriteKittiCalibration(source, target, [&](const std::string& name, double* v) {
    if (name == "P1:") baseline_m = -v[3] / v[0];
    if (mirror) v[2] = (width - 1) - v[2];
  });

  std::ofstream times_out(target / "times.txt");
  Trajectory poses_out;
  for (size_t k = 0; k < n; ++k) {
    const size_t i = reverse ? n - 1 - k : k;
    char from[32], to[32];
    std::snprintf(from, sizeof(from), "%06zu.png", i);
    std::snprintf(to, sizeof(to), "%06zu.png", k);
    for (const char* camera : {"image_0", "image_1"}) {
      if (!fs::exists(source / camera / from)) continue;
      const std::string other = std::string(camera) == "image_0" ? "image_1" : "image_0";
      const fs::path dir = target / (mirror && stereo ? other : std::string(camera));
      fs::create_directories(dir);
      if (!mirror) {
        fs::create_symlink(source / camera / from, dir / to);
        continue;
      }
      cv::Mat image = cv::imread((source / camera / from).string(), cv::IMREAD_UNCHANGED), flipped;
      cv::flip(image, flipped, 1);
      cv::imwrite((dir / to).string(), flipped);
    }
    times_out << times[k] << "\n";
    TimedPose pose = poses[i];
    if (mirror) {
      // M T M with M = diag(-1, 1, 1) on rotation and translation; with stereo, the new left
      // camera is the old right one: one baseline along the mirrored camera's -x.
      Eigen::Isometry3d& T = pose.T_world_cam;
      const Eigen::Matrix3d M = Eigen::Vector3d(-1, 1, 1).asDiagonal();
      T.linear() = M * T.linear() * M;
      T.translation() = M * T.translation();
      if (stereo) T.translation() -= baseline_m * T.linear().col(0);
    }
    poses_out.push_back(pose);
  }
  WriteKitti(root / "poses" / (sequence + ".txt"), poses_out);
  return target;
}

// Real images, motions the snippets do not have: KITTI 06 stereo driven backward and in a mirror;
// KITTI 07 monocular the same (mirrored, its 90-degree turn turns the other way). Nothing in the
// system is told. Bars: stereo, the snippet's own (ORB-SLAM2's 0.059 m on the original frames),
// 0 lost, scale within 1%; monocular, no frame lost after the start and Sim(3) ATE under 0.5% of
// the path (the bar of the other changed-motion runs). Measured: docs/STATUS.md.
TEST(SlamRun, KittiDrivenBackwardAndInAMirror) {
  for (const auto& [reverse, mirror] : {std::pair{true, false}, std::pair{false, true}}) {
    const std::string what = std::string(reverse ? "reversed " : "") + (mirror ? "mirrored" : "");
    const RunOutcome stereo = RunAndScore(KittiReversedOrMirrored("06", reverse, mirror).string(), false, 0);
    EXPECT_EQ(stereo.lost, 0u) << what;
    EXPECT_EQ(stereo.run.trajectory.size(), 51u) << what;
    EXPECT_LT(stereo.se3.ate_m.rmse, 0.059) << what;
    EXPECT_NEAR(stereo.sim3.alignment.scale, 1.0, 0.01) << what;

    const RunOutcome mono =
        RunAndScore(KittiReversedOrMirrored("07", reverse, mirror).string(), false, 0, Sensor::kMonocular);
    const size_t first_tracked = FirstTracked(mono.run);
    EXPECT_LE(first_tracked, 10u) << what;
    EXPECT_EQ(mono.run.trajectory.size(), mono.run.reports.size() - first_tracked) << what;
    EXPECT_LT(mono.sim3.ate_m.rmse, 0.005 * mono.path_m) << what;
  }
}

TEST(SlamRun, KittiMonocularSnippet) {
  const auto seq = testing::DatasetsDir() / "kitti" / "sequences" / "07";
  // As `flatslam run` runs it: the camera checked against the young map.
  const RunOutcome o = RunAndScore(seq.string(), false, 0, std::nullopt, true);
  const size_t first_tracked = FirstTracked(o.run);
  EXPECT_LE(first_tracked, 10u);                                             // ORB-SLAM2 initializes at frame 5
  EXPECT_EQ(o.run.trajectory.size(), o.run.reports.size() - first_tracked);  // nothing lost after that
  // The snippet's map asks for a radial term (k1 about +0.015, docs/STATUS.md), the run starts
  // over with it within the first fifth of its frames, and the refined camera's own check agrees.
  EXPECT_EQ(o.run.camera_restarts, 1u);
  EXPECT_GT(o.run.camera_refit.k1, 0.005);
  EXPECT_LE(o.run.frames_before_restart, o.run.reports.size() / 5 + 1);
  EXPECT_TRUE(o.run.camera_check.ok);
  EXPECT_FALSE(CameraCheckDisagrees(o.run.camera_check));
  // Bar: the issue's, ORB-SLAM2's 0.283 m after Sim(3). Measured with the refined camera
  // 0.1008 / 0.1005 / 0.1005 / 0.0985 m at seeds 1-4 (with the given one 0.2807 / 0.2696 /
  // 0.2884 / 0.3020); held to half the bar.
  EXPECT_LE(o.sim3.ate_m.rmse, 0.283 / 2);
}

// Local mapping running behind tracking (up to 3 keyframes): tracking outruns mapping on this
// snippet and used to lose the map around frame 40 in some runs. Tracking now waits while it
// wants a keyframe that mapping is too busy to take, and local BA ends early for it. With the
// cores shared (ctest -j2), a fading frame that waited for idle mapping before becoming a
// keyframe lost the map in 3 of 63 runs (frame 47 or 147); it is now queued at once. The timing
// differs from run to run, so the bound on the error is looser than in the waiting mode.
TEST(SlamRun, KittiMonocularWithMappingBehindLosesNothing) {
  const auto seq = testing::DatasetsDir() / "kitti" / "sequences" / "07";
  const auto dataset = OpenDataset(seq.string());
  // The vocabulary: monocular triangulation matches under vocabulary nodes.
  SlamOptions options = testing::OptionsWithDefaultVocabulary();
  options.orb.features = 2000;
  SlamRunOptions run;
  run.max_mapping_lag = 3;
  for (int attempt = 0; attempt < 3; ++attempt) {
    const SlamRunResult r = RunSlam(*dataset, options, run);
    size_t first_tracked = r.reports.size(), lost_after = 0;
    for (const FrameReport& f : r.reports) {
      if (f.state == TrackingState::kOk)
        first_tracked = std::min(first_tracked, f.index);
      else if (f.index > first_tracked)
        ++lost_after;
    }
    EvalOptions eval;
    eval.alignment = Alignment::kSim3;
    const double ate = Evaluate(*dataset->ground_truth(), r.trajectory, eval).ate_m.rmse;
    std::printf("run %d: first tracked frame %zu, %zu lost after it, %zu keyframes, Sim(3) ATE %.4f m\n", attempt,
                first_tracked, lost_after, r.keyframe_count, ate);
    EXPECT_LE(first_tracked, 10u);
    EXPECT_EQ(lost_after, 0u);
    EXPECT_EQ(r.trajectory.size(), r.reports.size() - first_tracked);
    EXPECT_LT(ate, 0.5);
  }
}

// A long session must not grow the map while it keeps revisiting the same place. The room's loop
// is 537 frames; over laps 3 and 4 the default options make 6 keyframes and the map ends 4 above
// its size after lap 2 (with `revisit_radius` 0, ORB-SLAM2's rules alone: 26 made, +11).
TEST(SlamRun, RevisitsKeepTheMapBounded) {
  const RunOutcome o = RunAndScore("synth:room:duration=100,width=480,height=360", false);
  ASSERT_EQ(o.run.reports.size(), 2000u);
  EXPECT_EQ(o.lost, 0u);
  EXPECT_LT(o.se3.ate_m.rmse, 0.01 * o.path_m);
  constexpr size_t kTwoLaps = 2 * 537;
  size_t made_after = 0;
  for (size_t i = kTwoLaps; i < o.run.reports.size(); ++i) made_after += o.run.reports[i].keyframe;
  const size_t after_two_laps = o.run.reports[kTwoLaps - 1].map_keyframes;
  std::printf("keyframes: %zu after two laps, %zu at the end, %zu made in laps 3-4\n", after_two_laps,
              o.run.reports.back().map_keyframes, made_after);
  EXPECT_LE(made_after, 10u);
  EXPECT_LE(o.run.reports.back().map_keyframes, after_two_laps + 6);
}

TEST(SlamRun, MonocularRoomAfterSim3) {
  const RunOutcome o = RunAndScore("synth:room:duration=20,width=480,height=360,sensor=mono", false);
  EXPECT_GT(o.run.trajectory.size(), 300u);
  EXPECT_LT(o.sim3.ate_m.rmse, 0.02 * o.path_m);
}

// A monocular run checks its camera model against its young map (SlamRunOptions::check_camera).
struct CheckedRun {
  SlamRunResult run;
  std::vector<size_t> heard;  // frame indices on_frame heard, in order
  double sim3_m = 0, path_m = 0;
};

CheckedRun RunCheckingCamera(const std::string& spec, bool check_camera, uint64_t seed = 0) {
  const auto dataset = OpenDataset(spec);
  SlamRunOptions run;
  run.deterministic = true;
  run.check_camera = check_camera;
  CheckedRun out;
  run.on_frame = [&](const FrameReport& r) { out.heard.push_back(r.index); };
  SlamOptions options = testing::OptionsWithDefaultVocabulary();
  if (seed != 0) options.seed = seed;
  out.run = RunSlam(*dataset, options, run);
  const testing::TrajectoryScore score = testing::ScoreTrajectory(*dataset->ground_truth(), out.run.trajectory);
  out.sim3_m = score.sim3.ate_m.rmse;
  out.path_m = score.path_m;
  std::printf("%s, check %d: %zu frames heard, %zu restarts after %zu frames (k1 %+.4f, fx x %.4f), Sim(3) %.4f m\n",
              spec.c_str(), check_camera, out.heard.size(), out.run.camera_restarts, out.run.frames_before_restart,
              out.run.camera_refit.k1, out.run.camera_refit.focal_scale, out.sim3_m);
  return out;
}

bool HeardEachFrameOnceInOrder(const CheckedRun& r, size_t frames) {
  if (r.heard.size() != frames) return false;
  for (size_t i = 0; i < frames; ++i)
    if (r.heard[i] != i) return false;
  return true;
}

// The room seen through a lens its calibration leaves out (k1 = 0.03 moves the corners of the
// 480x360 image by about 7 px): the check disagrees within the first fifth of the frames, the run
// starts over with the refined camera (again if that one's check still disagrees), and what the
// caller hears is the last pass alone.
TEST(SlamRun, AMonocularRunRefinesALensItsCalibrationLeavesOutAndStartsOver) {
  const std::string spec = "synth:room:duration=12,width=480,height=360,sensor=mono,k1=0.03";
  const CheckedRun kept = RunCheckingCamera(spec, false);
  const CheckedRun refined = RunCheckingCamera(spec, true);
  const size_t frames = kept.run.frames;
  ASSERT_TRUE(refined.run.camera_refit.refined());
  EXPECT_GE(refined.run.camera_restarts, 1u);
  EXPECT_LE(refined.run.camera_restarts, CameraCheckWindow::kMaxRestarts);
  EXPECT_NEAR(refined.run.camera_refit.k1, 0.03, 0.006);
  EXPECT_LE(refined.run.frames_before_restart, refined.run.camera_restarts * (frames / 5 + 1));
  // The images undistorted by the refined model: a camera other than the given one.
  EXPECT_NE(refined.run.calibration.camera.fx, kept.run.calibration.camera.fx);
  EXPECT_TRUE(HeardEachFrameOnceInOrder(refined, frames));
  EXPECT_EQ(refined.run.frames, frames);
  EXPECT_LT(refined.sim3_m, 0.5 * kept.sim3_m);
  // The pass that went on made its first frames from the keypoints the first pass measured in the
  // same images, moved through its own lens: it is the run over the refined images from the start.
  EXPECT_GT(refined.run.frames_from_kept_keypoints, 0u);
  EXPECT_LE(refined.run.frames_from_kept_keypoints,
            std::min(CameraCheckWindow::kKeptFrames, refined.run.frames_before_restart + 64));
  ASSERT_FALSE(refined.run.camera_refined_at_end);  // else its map moved after the last frame
  SlamRunOptions run;
  run.deterministic = true;
  const SlamRunResult direct = RunSlam(*ApplyCameraRefit(OpenDataset(spec), refined.run.camera_refit_tracked),
                                       testing::OptionsWithDefaultVocabulary(), run);
  EXPECT_EQ(direct.frames_from_kept_keypoints, 0u);
  ASSERT_EQ(direct.trajectory.size(), refined.run.trajectory.size());
  for (size_t i = 0; i < direct.trajectory.size(); ++i)
    EXPECT_TRUE(direct.trajectory[i].T_world_cam.isApprox(refined.run.trajectory[i].T_world_cam, 1e-12)) << i;
}

// The street seen by KITTI's camera through a lens its calibration leaves out (k1 = 0.02 moves
// the image's corners by about 9 px), at a seed whose young map, moving forward along a straight
// stretch, absorbs part of the lens and leaves the rest within its noise: nothing starts over.
// After the last frame the whole map, turns included, disagrees; its keypoints move into the
// refined camera and it is adjusted there, which takes out the scale its turns took from the
// wrong model (Sim(3) 0.69 -> 0.08 m when written).
TEST(SlamRun, AMonocularMapWhoseYoungPartCannotTellItsLensIsRefinedAfterItsLastFrame) {
  const std::string spec =
      "synth:street:width=1226,height=370,fx=707,fps=10,duration=20,k1=0.02,sensor=mono,seed=2";
  const CheckedRun kept = RunCheckingCamera(spec, false, 2);
  const CheckedRun refined = RunCheckingCamera(spec, true, 2);
  EXPECT_EQ(refined.run.camera_restarts, 0u);
  EXPECT_FALSE(refined.run.camera_refit_tracked.refined());
  ASSERT_TRUE(refined.run.camera_refined_at_end);
  EXPECT_TRUE(CameraCheckDisagrees(refined.run.camera_check_at_end));
  EXPECT_NEAR(refined.run.camera_refit.k1, 0.02, 0.006);
  EXPECT_NEAR(refined.run.camera_refit.focal_scale, 1, 0.01);
  // The calibration the map is in: the refined camera's, as ApplyCameraRefit gives it.
  const auto dataset = OpenDataset(spec);
  EXPECT_NEAR(refined.run.calibration.camera.fx,
              ApplyCameraRefit(OpenDataset(spec), refined.run.camera_refit)->calibration().camera.fx, 1e-9);
  EXPECT_EQ(refined.run.camera_tracked.fx, dataset->calibration().camera.fx);
  EXPECT_GT(refined.run.camera_end_keypoints, 0u);
  EXPECT_TRUE(HeardEachFrameOnceInOrder(refined, kept.run.frames));
  EXPECT_LT(refined.sim3_m, 0.3 * kept.sim3_m);
}

// The exact camera: the checks agree, nothing starts over, and the run is the run without checks.
TEST(SlamRun, AMonocularRunWhoseMapAgreesWithItsCameraRunsOnce) {
  const std::string spec = "synth:room:duration=12,width=480,height=360,sensor=mono";
  const CheckedRun plain = RunCheckingCamera(spec, false);
  const CheckedRun checked = RunCheckingCamera(spec, true);
  EXPECT_FALSE(checked.run.camera_refit.refined());
  EXPECT_TRUE(checked.run.camera_check.ok);
  EXPECT_FALSE(CameraCheckDisagrees(checked.run.camera_check));
  EXPECT_TRUE(HeardEachFrameOnceInOrder(checked, plain.run.frames));
  ASSERT_EQ(checked.run.trajectory.size(), plain.run.trajectory.size());
  for (size_t i = 0; i < plain.run.trajectory.size(); ++i)
    EXPECT_TRUE(checked.run.trajectory[i].T_world_cam.isApprox(plain.run.trajectory[i].T_world_cam, 1e-12)) << i;
}

}  // namespace
}  // namespace flatslam
