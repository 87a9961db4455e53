// RunSlam keeps a session going and resumable: unreadable frames are skipped (or stop a strict
// run), a stop request ends the run with results over the frames tracked, and checkpoints carry
// what a continuation needs to give the trajectory of every frame.
#include <gtest/gtest.h>

#include <atomic>
#include <set>
#include <string>

#include "core/error.h"
#include "jobs/slam_runner.h"
#include "default_vocabulary.h"
#include "place/vocabulary.h"
#include "trajectory_score.h"

namespace flatslam {
namespace {

using testing::OptionsWithDefaultVocabulary;

// A synthetic dataset whose listed frames cannot be read.
class DamagedDataset final : public Dataset {
 public:
  DamagedDataset(std::unique_ptr<Dataset> inner, std::set<size_t> bad)
      : inner_(std::move(inner)), bad_(std::move(bad)) {}
  std::string name() const override { return inner_->name(); }
  const Calibration& calibration() const override { return inner_->calibration(); }
  size_t size() const override { return inner_->size(); }
  Frame read(size_t i) const override {
    if (bad_.count(i)) Fail("cannot decode image (unreadable or truncated): frame_", i, ".png");
    return inner_->read(i);
  }
  std::optional<Trajectory> ground_truth() const override { return inner_->ground_truth(); }

 private:
  std::unique_ptr<Dataset> inner_;
  std::set<size_t> bad_;
};

const char* const kRoom = "synth:room:duration=20,width=480,height=360";

TEST(SessionRun, UnreadableFramesAreSkippedLikeDroppedFrames) {
  const DamagedDataset dataset(OpenDataset(kRoom), {10, 11, 40});
  SlamRunOptions run;
  std::vector<std::pair<size_t, std::string>> heard;
  run.on_skipped = [&](size_t index, const std::string& reason) { heard.emplace_back(index, reason); };
  const SlamRunResult result = RunSlam(dataset, OptionsWithDefaultVocabulary(), run);
  EXPECT_EQ(result.frames, dataset.size());
  EXPECT_EQ(result.frames_skipped, 3u);
  ASSERT_EQ(heard.size(), 3u);
  EXPECT_EQ(heard[0].first, 10u);
  EXPECT_EQ(heard[2].first, 40u);
  EXPECT_NE(heard[0].second.find("frame_10.png"), std::string::npos) << heard[0].second;
  ASSERT_EQ(result.reports.size(), dataset.size());
  EXPECT_TRUE(result.reports[11].skipped);
  EXPECT_FALSE(result.reports[12].skipped);
  // Tracking went on around the gaps: every other frame is in the trajectory.
  EXPECT_EQ(result.trajectory.size(), dataset.size() - 3);
  const auto score = testing::ScoreTrajectory(*dataset.ground_truth(), result.trajectory);
  EXPECT_LT(score.se3.ate_m.rmse, 0.01 * score.path_m);
}

TEST(SessionRun, StrictRunStopsAtTheFirstUnreadableFrame) {
  const DamagedDataset dataset(OpenDataset(kRoom), {10});
  SlamRunOptions run;
  run.strict = true;
  try {
    (void)RunSlam(dataset, OptionsWithDefaultVocabulary(), run);
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("frame_10.png"), std::string::npos) << e.what();
  }
}

TEST(SessionRun, NoReadableFrameIsAnError) {
  std::set<size_t> all;
  for (size_t i = 0; i < 30; ++i) all.insert(i);
  const DamagedDataset dataset(OpenDataset(kRoom), all);
  SlamRunOptions run;
  run.max_frames = 30;
  try {
    (void)RunSlam(dataset, OptionsWithDefaultVocabulary(), run);
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("none of the 30 frames"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("frame_0.png"), std::string::npos) << e.what();
  }
}

TEST(SessionRun, StopEndsTheRunWithResultsOverTheFramesTracked) {
  const auto dataset = OpenDataset(kRoom);
  std::atomic<bool> stop{false};
  SlamRunOptions run;
  run.stop = &stop;
  run.on_frame = [&](const FrameReport& r) {
    if (r.index == 50) stop = true;
  };
  const SlamRunResult result = RunSlam(*dataset, OptionsWithDefaultVocabulary(), run);
  EXPECT_TRUE(result.interrupted);
  // Frames already read when the stop came are tracked; none after.
  EXPECT_GE(result.frames, 51u);
  EXPECT_LT(result.frames, 51u + 64u);
  EXPECT_EQ(result.next_frame, result.frames);
  EXPECT_EQ(result.trajectory.size(), result.frames);
}

// Checkpoints every 50 ms: each holds a valid map and the frames it covers, and a continuation from
// one (the checkpoint's map, trajectory and next frame) gives a trajectory of every frame.
TEST(SessionRun, ACheckpointContinuesToTheTrajectoryOfEveryFrame) {
  const auto dataset = OpenDataset(kRoom);
  const SlamOptions options = OptionsWithDefaultVocabulary();
  SlamRunOptions run;
  run.checkpoint_every_s = 0.05;
  // What each checkpoint would save: its map and its frames anchored in that map.
  std::vector<Map> maps;
  std::vector<std::vector<AnchoredFramePose>> frames;
  std::vector<size_t> next_frames;
  size_t flushed_before = 0, reported = 0;
  run.on_frame = [&](const FrameReport&) { ++reported; };
  run.before_checkpoint = [&] { flushed_before = reported; };
  run.on_checkpoint = [&](const SlamSession::State& state, size_t next_frame) {
    EXPECT_EQ(next_frame, state.next_frame);
    // Every frame the checkpoint covers was reported before it was taken.
    EXPECT_LE(next_frame, flushed_before);
    EXPECT_TRUE(state.map.Validate().empty()) << state.map.Validate();
    maps.push_back(state.map);
    frames.emplace_back();
    state.AnchoredToMap(&frames.back());
    for (const AnchoredFramePose& f : frames.back())
      EXPECT_TRUE(f.reference.is_null() || state.map.keyframes().contains(f.reference));
    next_frames.push_back(next_frame);
  };
  const SlamRunResult whole = RunSlam(*dataset, options, run);
  ASSERT_GE(maps.size(), 3u);
  EXPECT_EQ(whole.checkpoints, maps.size());
  EXPECT_EQ(next_frames.back(), dataset->size());  // the last one covers the whole run
  EXPECT_EQ(frames.back().size(), whole.trajectory.size());
  const auto whole_score = testing::ScoreTrajectory(*dataset->ground_truth(), whole.trajectory);

  // The checkpoints taken before the end continue to a trajectory of every frame.
  std::vector<size_t> before_end;
  for (size_t k = 0; k < maps.size(); ++k)
    if (next_frames[k] < dataset->size()) before_end.push_back(k);
  ASSERT_GE(before_end.size(), 2u);
  for (size_t k : {before_end.front(), before_end.back()}) {
    SlamRunOptions rest;
    Map map = maps[k];
    rest.initial_map = &map;
    rest.initial_frames = frames[k];
    rest.first_frame = next_frames[k];
    const SlamRunResult continued = RunSlam(*dataset, options, rest);
    EXPECT_EQ(continued.trajectory.size(), dataset->size()) << "continued from frame " << next_frames[k];
  }
}

// A session captured after frame N and continued from there (deterministic mapping, so the frames
// are chosen, not the timer's) is as accurate as the uninterrupted run, at the run's quarter
// points. The continuation tracks on from the last two frames' motion (it never relocalizes); the
// room's trajectory still reacts chaotically to the resume: over capture frames 100-300 every
// 10, one continuation ends at 1.53x the uninterrupted ATE, the others between 0.87x and 1.32x
// (docs/STATUS.md, sessions).
TEST(SessionRun, AContinuedSessionIsAsAccurateAsTheWholeRun) {
  const auto dataset = OpenDataset(kRoom);
  const SlamOptions options = OptionsWithDefaultVocabulary();
  SlamRunOptions all;
  all.deterministic = true;
  const SlamRunResult whole = RunSlam(*dataset, options, all);
  const auto whole_score = testing::ScoreTrajectory(*dataset->ground_truth(), whole.trajectory);
  const size_t n = dataset->size();
  for (size_t k : {n / 4, n / 2, 3 * n / 4}) {
    SlamRunOptions first;
    first.deterministic = true;
    first.max_frames = k;
    Map map;
    std::vector<AnchoredFramePose> frames;
    first.on_finished = [&](const SlamSession& slam) {
      SlamSession::State state;
      slam.CaptureState(&state);
      state.AnchoredToMap(&frames);
      map = state.map;
    };
    (void)RunSlam(*dataset, options, first);
    SlamRunOptions rest;
    rest.deterministic = true;
    rest.initial_map = &map;
    rest.initial_frames = frames;
    rest.first_frame = k;
    const SlamRunResult continued = RunSlam(*dataset, options, rest);
    ASSERT_EQ(continued.trajectory.size(), n);
    size_t relocalized = 0;
    for (const FrameReport& r : continued.reports) relocalized += r.relocalized;
    EXPECT_EQ(relocalized, 0u) << "the continuation from frame " << k << " should track on, not relocalize";
    const auto score = testing::ScoreTrajectory(*dataset->ground_truth(), continued.trajectory);
    std::printf("whole run ATE %.4f m; continued from frame %zu: ATE %.4f m\n", whole_score.se3.ate_m.rmse, k,
                score.se3.ate_m.rmse);
    EXPECT_LT(score.se3.ate_m.rmse, 1.5 * whole_score.se3.ate_m.rmse) << "continued from frame " << k;
  }
}

// A checkpoint whose copy caught the global bundle adjustment after a loop still running holds the
// loop's correction without the adjustment; the resumed session runs it again. The copy here is
// taken (deterministically) from a run whose adjustment after its loop (the 32-s room closes one
// at frame 562) is switched off: the map such a copy holds.
TEST(SessionRun, AResumedCheckpointRunsTheGlobalAdjustmentItCaughtRunning) {
  const auto dataset = OpenDataset("synth:room:duration=32,width=480,height=360");
  const size_t n = dataset->size(), k = 600;
  SlamOptions options = OptionsWithDefaultVocabulary();
  options.global_bundle_adjustment = false;
  SlamRunOptions first;
  first.deterministic = true;
  first.max_frames = k;
  Map map;
  std::vector<AnchoredFramePose> frames;
  size_t loops = 0;
  first.on_finished = [&](const SlamSession& slam) {
    SlamSession::State state;
    slam.CaptureState(&state);
    EXPECT_FALSE(state.global_adjustment_pending);  // none ran
    state.AnchoredToMap(&frames);
    map = state.map;
    loops = slam.loop_closures().size();
  };
  (void)RunSlam(*dataset, options, first);
  ASSERT_EQ(loops, 1u) << "the room's loop closes before frame " << k;
  options.global_bundle_adjustment = true;
  double ate[2] = {0, 0};
  uint64_t corrections[2] = {0, 0};
  for (int pending = 0; pending < 2; ++pending) {
    Map copy = map;
    SlamRunOptions rest;
    rest.deterministic = true;
    rest.initial_map = &copy;
    rest.initial_frames = frames;
    rest.first_frame = k;
    rest.initial_global_adjustment = pending == 1;
    rest.on_finished = [&](const SlamSession& slam) { corrections[pending] = slam.map_corrections(); };
    const SlamRunResult continued = RunSlam(*dataset, options, rest);
    ASSERT_EQ(continued.trajectory.size(), n);
    ate[pending] = testing::ScoreTrajectory(*dataset->ground_truth(), continued.trajectory).se3.ate_m.rmse;
  }
  std::printf("resumed at frame %zu without the adjustment: ATE %.4f m; with it: ATE %.4f m\n", k, ate[0], ate[1]);
  EXPECT_EQ(corrections[0], 0u);  // nothing moved the adopted map's keyframes
  EXPECT_EQ(corrections[1], 1u);  // the adjustment, once
  EXPECT_LT(ate[1], ate[0]);
}

}  // namespace
}  // namespace flatslam
