// Batches: every sequence gives what its own run gives, a failing one does not stop the others,
// a stop flag ends the batch with every row written, and the memory budget's admission rule.
#include "jobs/batch.h"

#include <gtest/gtest.h>


#include "jobs/sequence_run.h"
#include "place/vocabulary.h"
#include "test_data.h"

namespace flatslam {
namespace {

using testing::ReadBytes;

SequenceSpec Spec(const std::string& name, const std::string& dataset) {
  SequenceSpec s;
  s.name = name;
  s.dataset = dataset;
  return s;
}

TEST(Batch, EachSequenceGivesItsSingleRunAndAFailureStopsNoOther) {
  const auto dir = testing::FreshTempDir("batch_runs");
  const Vocabulary vocabulary = Vocabulary::Load(DefaultVocabularyPath());
  std::vector<SequenceSpec> specs = {
      Spec("room", "synth:room:duration=3"), Spec("broken", (dir / "no_such_dataset").string()),
      Spec("room_rgbd", "synth:room:duration=3,sensor=rgbd"),
      Spec("corridor_mono", "synth:corridor:duration=3,sensor=mono"), Spec("bad_option", "synth:room:duration=3")};
  specs.back().set = {"orb.features=-5"};
  BatchOptions options;
  options.jobs = 3;
  options.vocabulary = &vocabulary;
  options.deterministic = true;
  options.out_dir = dir / "batch";
  size_t progress_calls = 0;
  BatchProgress last;
  options.on_progress = [&](const BatchProgress& p) {
    ++progress_calls;
    EXPECT_LE(p.running, options.jobs);
    last = p;
  };
  std::vector<std::string> finished;
  options.on_finished = [&](const SequenceResult& r) { finished.push_back(r.name); };
  const std::vector<SequenceResult> results = RunBatch(specs, {10, 11, 12, 13, 14}, options);
  ASSERT_EQ(results.size(), specs.size());
  EXPECT_EQ(finished.size(), specs.size());
  EXPECT_GE(progress_calls, 1u);
  EXPECT_EQ(last.finished, specs.size());
  EXPECT_EQ(last.running, 0u);
  for (size_t i = 0; i < specs.size(); ++i) {
    EXPECT_EQ(results[i].name, specs[i].name);
    EXPECT_EQ(results[i].input, 10 + i);
  }
  EXPECT_EQ(results[1].status, "failed");
  EXPECT_NE(results[1].error.find("no_such_dataset"), std::string::npos) << results[1].error;
  EXPECT_EQ(results[4].status, "failed");
  EXPECT_NE(results[4].error.find("orb.features"), std::string::npos) << results[4].error;
  // The failed ones still leave their row.
  EXPECT_TRUE(std::filesystem::exists(dir / "batch" / "broken" / "results.csv"));

  for (size_t i : {0u, 2u, 3u}) {
    const SequenceResult& r = results[i];
    EXPECT_EQ(r.status, "ok") << r.name << ": " << r.error;
    EXPECT_EQ(r.frames, 60u) << r.name;
    EXPECT_GT(r.keyframes, 0u);
    ASSERT_TRUE(r.ate_sim3_m.has_value()) << r.name;
    EXPECT_LT(*r.ate_sim3_m, 0.05) << r.name;
    EXPECT_GT(r.cpu_ms_per_frame, 0);
    EXPECT_GT(r.peak_rss_mib, 0);
    // The same sequence alone, deterministic: the same trajectory to the last digit.
    SequenceRunOptions alone;
    alone.vocabulary = &vocabulary;
    alone.deterministic = true;
    alone.out_dir = dir / "alone" / r.name;
    const SequenceResult single = RunSequence(specs[i], alone);
    ASSERT_EQ(single.status, "ok");
    const std::string batch_poses = ReadBytes(dir / "batch" / r.name / "trajectory.tum");
    EXPECT_FALSE(batch_poses.empty());
    EXPECT_EQ(batch_poses, ReadBytes(alone.out_dir / "trajectory.tum")) << r.name;
    EXPECT_EQ(single.ate_se3_m, r.ate_se3_m) << r.name;
    for (const char* file : {"stats.csv", "trajectory.kitti", "keyframes.tum", "groundtruth.tum", "results.csv"})
      EXPECT_TRUE(std::filesystem::exists(dir / "batch" / r.name / file)) << r.name << "/" << file;
  }
}

// A monocular sequence checks its camera as flatslam run does: the room seen through a lens its
// calibration leaves out (k1 = 0.03) starts over with the refined camera and its row says which;
// keep_camera (a manifest's or the batch's --keep-camera) runs it with the given camera.
TEST(SequenceRun, AMonocularSequenceRecordsTheCameraItRefinedUnlessItKeepsItsOwn) {
  const auto dir = testing::FreshTempDir("sequence_refit");
  SequenceSpec spec = Spec("lens", "synth:room:duration=8,width=480,height=360,sensor=mono,k1=0.03");
  SequenceRunOptions options;
  options.deterministic = true;
  options.out_dir = dir / "checked";
  const SequenceResult checked = RunSequence(spec, options);
  ASSERT_EQ(checked.status, "ok") << checked.error;
  ASSERT_TRUE(checked.camera_refit_k1.has_value());
  EXPECT_NEAR(*checked.camera_refit_k1, 0.03, 0.008);
  ASSERT_TRUE(checked.camera_refit_focal_scale.has_value());
  EXPECT_NEAR(*checked.camera_refit_focal_scale, 1, 0.02);
  const std::vector<SequenceResult> row = ReadResultsCsv(options.out_dir / "results.csv");
  ASSERT_EQ(row.size(), 1u);
  ASSERT_TRUE(row[0].camera_refit_k1.has_value());
  EXPECT_NEAR(*row[0].camera_refit_k1, *checked.camera_refit_k1, 1e-5);  // the file's 5 decimals

  spec.keep_camera = true;
  options.out_dir = dir / "kept";
  const SequenceResult kept = RunSequence(spec, options);
  ASSERT_EQ(kept.status, "ok") << kept.error;
  EXPECT_FALSE(kept.camera_refit_k1.has_value());
  EXPECT_EQ(kept.frames, checked.frames);
  ASSERT_TRUE(kept.ate_sim3_m && checked.ate_sim3_m);
  EXPECT_LT(*checked.ate_sim3_m, *kept.ate_sim3_m);
}

TEST(Batch, AStopFlagEndsTheBatchWithEveryRow) {
  const auto dir = testing::FreshTempDir("batch_stop");
  std::vector<SequenceSpec> specs;
  for (int k = 0; k < 4; ++k) specs.push_back(Spec("room" + std::to_string(k), "synth:room:duration=20"));
  std::atomic<bool> stop{false};
  BatchOptions options;
  options.jobs = 2;
  options.out_dir = dir;
  options.stop = &stop;
  options.on_progress = [&](const BatchProgress& p) {
    if (p.frames_done >= 20) stop = true;
  };
  options.progress_interval_s = 0.05;
  const auto results = RunBatch(specs, {0, 1, 2, 3}, options);
  ASSERT_EQ(results.size(), 4u);
  size_t interrupted = 0;
  for (const SequenceResult& r : results) {
    interrupted += r.status == "interrupted";
    EXPECT_NE(r.status, "failed") << r.error;
    EXPECT_LT(r.frames, 400u) << r.name;  // none ran to its end
  }
  EXPECT_EQ(interrupted, 4u);
  // The two never started say so; the two stopped wrote what they tracked.
  EXPECT_EQ(results[3].error, "not started: the batch was interrupted");
  EXPECT_GT(results[0].tracked, 0u);
  EXPECT_TRUE(std::filesystem::exists(dir / "room0" / "trajectory.tum"));
}

// A monocular run that loses tracking waits for a new two-view start in the not-initialized
// state: those frames are lost frames, not frames before initialization.
TEST(RunRecorder, FramesWithoutAPoseAfterTheFirstPoseAreLost) {
  using S = TrackingState;
  const struct {
    S state;
    bool pose;
  } frames[] = {{S::kNotInitialized, false},
                {S::kNotInitialized, false},
                {S::kOk, true},
                {S::kLost, false},
                {S::kNotInitialized, false},
                {S::kNotInitialized, false},
                {S::kOk, true},
                {S::kLost, false},
                {S::kOk, true}};
  RunRecorder recorder(std::nullopt);
  size_t index = 0;
  for (const auto& f : frames) {
    FrameReport r;
    r.index = index++;
    r.state = f.state;
    if (f.pose) r.T_world_cam = Eigen::Isometry3d::Identity();
    r.inliers = f.pose ? static_cast<int>(100 + index) : 3;
    recorder.OnFrame(r);
  }
  EXPECT_EQ(recorder.counts().frames, 9u);
  EXPECT_EQ(recorder.counts().not_initialized, 2u);
  EXPECT_EQ(recorder.counts().lost, 4u);
  // Two stretches lost, after the frames 2 and 6 (index + 1 inliers above).
  EXPECT_EQ(recorder.counts().lost_stretches, 2u);
  EXPECT_EQ(recorder.counts().inliers_before_loss, (std::vector<int>{103, 107}));

  // A resumed run has had its first pose: a frame waiting to start is lost.
  const std::vector<AnchoredFramePose> resumed(1);
  RunRecorder resumed_recorder(std::nullopt, 10, &resumed);
  FrameReport waiting;
  waiting.index = 10;
  waiting.state = S::kNotInitialized;
  resumed_recorder.OnFrame(waiting);
  EXPECT_EQ(resumed_recorder.counts().lost, 1u);
  EXPECT_EQ(resumed_recorder.counts().not_initialized, 0u);
  EXPECT_EQ(resumed_recorder.counts().lost_stretches, 1u);
  EXPECT_TRUE(resumed_recorder.counts().inliers_before_loss.empty());
}

TEST(Batch, MemoryBudgetAdmitsWhatFits) {
  // Nothing running: always (a sequence larger than the budget still runs, alone).
  EXPECT_TRUE(AdmitSequence(0, 5000, 100, 3000, 1000));
  // Two running of an estimated 200 MiB each from a 100 MiB baseline: a third fits 800 MiB...
  EXPECT_TRUE(AdmitSequence(2, 450, 100, 200, 800));
  // ...but not 600 MiB (projection 700), nor when the resident set is already high.
  EXPECT_FALSE(AdmitSequence(2, 450, 100, 200, 600));
  EXPECT_FALSE(AdmitSequence(1, 700, 100, 200, 800));
}

}  // namespace
}  // namespace flatslam
