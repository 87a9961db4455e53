// Multi-session mapping: a synthetic run cut into sections of 200 frames, each section saving the
// map and the next one loading it, relocalizing in it and extending it, must give the same map
// and trajectory as the uninterrupted run within tracking noise.
// Localization-only sessions track against a loaded map without changing it.
#include <cstdio>
#include <functional>
#include <vector>

#include <gtest/gtest.h>

#include "jobs/slam_runner.h"
#include "storage/snapshot.h"
#include "place/vocabulary.h"
#include "default_vocabulary.h"
#include "test_data.h"
#include "trajectory/metrics.h"

namespace flatslam {
namespace {

using testing::DefaultVocabulary;
using testing::OptionsWithDefaultVocabulary;

constexpr const char* kScene = "synth:room:duration=40,width=480,height=360";

double Ate(const Trajectory& gt, const Trajectory& estimate) {
  EvalOptions eval;
  eval.alignment = Alignment::kSE3;
  return Evaluate(gt, estimate, eval).ate_m.rmse;
}

// An on_finished that serializes the session's map into *bytes, as a snapshot of that calibration.
std::function<void(const SlamSession&)> SerializeMapInto(std::vector<uint8_t>* bytes, const Calibration& calibration) {
  return [bytes, calibration](const SlamSession& slam) {
    SnapshotMetadata metadata;
    metadata.calibration = calibration;
    const SnapshotMapRef ref{0, &slam.map()};
    *bytes = SerializeMapSnapshot({&ref, 1}, metadata);
  };
}

// The frames of [first, last) (by timestamp) of a trajectory.
Trajectory Slice(const Trajectory& trajectory, int64_t first_t_ns, int64_t last_t_ns) {
  Trajectory out;
  for (const TimedPose& p : trajectory)
    if (p.t_ns >= first_t_ns && p.t_ns < last_t_ns) out.push_back(p);
  return out;
}

TEST(ContinuedSession, SectionsOf200FramesMatchTheUninterruptedRun) {
  const auto dataset = OpenDataset(kScene);
  const Trajectory gt = *dataset->ground_truth();
  const SlamRunResult whole = RunSlam(*dataset, OptionsWithDefaultVocabulary(), SlamRunOptions{});
  const double whole_ate = Ate(gt, whole.trajectory);
  SlamRunResult last;

  const auto dir = testing::FreshTempDir("continued_session");
  const auto path = dir / "map.fsmp";
  SnapshotMetadata metadata;
  metadata.calibration = dataset->calibration();
  metadata.vocabulary_checksum = DefaultVocabulary().checksum();
  Trajectory joined;
  size_t lost = 0, reinitialized = 0, sections = 0;
  for (size_t first = 0; first < dataset->size(); first += 200) {
    SlamRunOptions run;
    run.first_frame = first;
    run.max_frames = first + 200;
    std::optional<Map> loaded;
    if (first > 0) {
      SnapshotReadOptions read;
      read.vocabulary_checksum = DefaultVocabulary().checksum();
      LoadedSnapshot snapshot = LoadMapSnapshot(path, read);
      ASSERT_EQ(snapshot.maps.size(), 1u);
      loaded = std::move(snapshot.maps[0].map);
      run.initial_map = &*loaded;
    }
    run.on_finished = [&](const SlamSession& slam) {
      const SnapshotMapRef ref{0, &slam.map()};
      SaveMapSnapshot(path, {&ref, 1}, metadata);
    };
    const SlamRunResult part = RunSlam(*dataset, OptionsWithDefaultVocabulary(), run);
    for (const FrameReport& r : part.reports) {
      lost += r.state != TrackingState::kOk;
      reinitialized += r.reinitialized;
    }
    joined.insert(joined.end(), part.trajectory.begin(), part.trajectory.end());
    ++sections;
    last = part;
  }
  // The map after the last section holds every section's keyframes, refined by everything that
  // happened since (the loop closed in the third section): it is compared with the uninterrupted
  // run's map. A section's frames are written when it ends and never see a correction made in a
  // later section, so the frames are compared where both runs know the same: the last section.
  const double whole_keyframes_ate = Ate(gt, whole.keyframes);
  const double map_ate = Ate(gt, last.keyframes);
  const int64_t last_section_t_ns = dataset->read(600).t_ns;
  const double whole_tail_ate = Ate(gt, Slice(whole.trajectory, last_section_t_ns, INT64_MAX));
  const double joined_tail_ate = Ate(gt, Slice(joined, last_section_t_ns, INT64_MAX));
  std::printf(
      "uninterrupted: frame ATE %.4f m over %zu frames, keyframe ATE %.4f m (%zu), last 200 frames %.4f m\n"
      "%zu sections: joined frame ATE %.4f m over %zu frames (%zu lost), final map keyframe ATE %.4f m (%zu), last "
      "200 frames %.4f m\n",
      whole_ate, whole.trajectory.size(), whole_keyframes_ate, whole.keyframes.size(), whole_tail_ate, sections,
      Ate(gt, joined), joined.size(), lost, map_ate, last.keyframes.size(), joined_tail_ate);
  EXPECT_EQ(sections, 4u);
  EXPECT_EQ(reinitialized, 0u) << "every section continues the one map";
  EXPECT_LE(lost, 2u * (sections - 1)) << "each section relocalizes within a frame or two";
  EXPECT_GE(joined.size(), dataset->size() - 2 * (sections - 1));
  // Same map and same trajectory within tracking noise.
  EXPECT_LT(map_ate, std::max(1.5 * whole_keyframes_ate, whole_keyframes_ate + 0.01));
  EXPECT_LT(joined_tail_ate, std::max(1.5 * whole_tail_ate, whole_tail_ate + 0.01));
  std::filesystem::remove_all(dir);
}

// A monocular session continued with the camera check (as flatslam run --load-map and --resume
// run it) checks the whole map after its last frame, and moves it into the camera it asks for:
// here a map built through a lens its calibration leaves out (k1 = 0.03), camera kept. Continued
// with localization only, the map stays as it is.
TEST(ContinuedSession, AMonocularContinuationChecksTheWholeMapAfterItsLastFrame) {
  const auto dataset = OpenDataset("synth:room:duration=8,width=480,height=360,sensor=mono,k1=0.03");
  SlamRunOptions first;
  first.deterministic = true;
  std::vector<uint8_t> saved;
  first.on_finished = SerializeMapInto(&saved, dataset->calibration());
  (void)RunSlam(*dataset, OptionsWithDefaultVocabulary(), first);
  for (const bool localize : {false, true}) {
    Map map = std::move(LoadMapSnapshotFromBytes(saved, "first session").maps[0].map);
    SlamOptions options = OptionsWithDefaultVocabulary();
    options.localization_only = localize;
    SlamRunOptions run;
    run.deterministic = true;
    run.check_camera = true;
    run.first_frame = 100;  // a stretch the map covers
    run.initial_map = &map;
    const SlamRunResult r = RunSlam(*dataset, options, run);
    EXPECT_GE(r.trajectory.size(), 50u) << localize;
    EXPECT_EQ(r.camera_restarts, 0u);
    EXPECT_EQ(r.camera_refined_at_end, !localize);
    if (localize) continue;
    EXPECT_TRUE(CameraCheckDisagrees(r.camera_check_at_end));
    EXPECT_NEAR(r.camera_refit.k1, 0.03, 0.008);
    EXPECT_NE(r.calibration.camera.fx, dataset->calibration().camera.fx);
    EXPECT_FALSE(r.camera_refit_tracked.refined());  // the frames were tracked through the given camera
  }
}

TEST(ContinuedSession, LocalizationOnlyLeavesTheMapUnchanged) {
  const auto dataset = OpenDataset(kScene);
  SlamRunOptions first;
  first.max_frames = 300;
  std::vector<uint8_t> before;
  first.on_finished = SerializeMapInto(&before, dataset->calibration());
  (void)RunSlam(*dataset, OptionsWithDefaultVocabulary(), first);
  LoadedSnapshot snapshot = LoadMapSnapshotFromBytes(before, "first session");
  Map map = std::move(snapshot.maps[0].map);

  SlamOptions options = OptionsWithDefaultVocabulary();
  options.localization_only = true;
  SlamRunOptions run;
  run.first_frame = 100;  // a stretch the map covers
  run.max_frames = 300;
  run.initial_map = &map;
  std::vector<uint8_t> after;
  run.on_finished = SerializeMapInto(&after, dataset->calibration());
  const SlamRunResult r = RunSlam(*dataset, options, run);
  size_t keyframes_made = 0;
  for (const FrameReport& f : r.reports) keyframes_made += f.keyframe;
  EXPECT_EQ(keyframes_made, 0u);
  EXPECT_GE(r.trajectory.size(), 195u);
  EXPECT_EQ(before, after) << "localization changed the map";
  EXPECT_LT(Ate(*dataset->ground_truth(), r.trajectory), 0.05);
}

}  // namespace
}  // namespace flatslam
