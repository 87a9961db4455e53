// Multi-session mapping: a synthetic run cut into sections of 200 frames, each section saving the
// map and the next one loading it, relocalizing in it and extending it, must give the same
// trajectory as the uninterrupted run within tracking noise (one alignment for all sections).
// Localization-only sessions track against a loaded map without changing it.
#include <cstdio>

#include <gtest/gtest.h>

#include "jobs/slam_runner.h"
#include "storage/snapshot.h"
#include "systems/vocabulary.h"
#include "test_data.h"
#include "trajectory/metrics.h"

namespace flatslam {
namespace {

const Vocabulary& DefaultVocabulary() {
  static const Vocabulary vocabulary = Vocabulary::Load(DefaultVocabularyPath());
  return vocabulary;
}

constexpr const char* kScene = "synth:room:duration=40,width=480,height=360";

SlamOptions Options() {
  SlamOptions options;
  options.vocabulary = &DefaultVocabulary();
  return options;
}

double Ate(const Trajectory& gt, const Trajectory& estimate) {
  EvalOptions eval;
  eval.alignment = Alignment::kSE3;
  return Evaluate(gt, estimate, eval).ate_m.rmse;
}

TEST(ContinuedSession, SectionsOf200FramesMatchTheUninterruptedRun) {
  const auto dataset = OpenDataset(kScene);
  const Trajectory gt = *dataset->ground_truth();
  const SlamRunResult whole = RunSlam(*dataset, Options(), SlamRunOptions{});
  const double whole_ate = Ate(gt, whole.trajectory);

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
    run.on_finished = [&](const Slam& slam) {
      const SnapshotMapRef ref{0, &slam.map()};
      SaveMapSnapshot(path, {&ref, 1}, metadata);
    };
    const SlamRunResult part = RunSlam(*dataset, Options(), run);
    for (const FrameReport& r : part.reports) {
      lost += r.state != TrackingState::kOk;
      reinitialized += r.reinitialized;
    }
    joined.insert(joined.end(), part.trajectory.begin(), part.trajectory.end());
    ++sections;
  }
  const double joined_ate = Ate(gt, joined);
  std::printf("uninterrupted ATE %.4f m over %zu frames; %zu sections joined ATE %.4f m, %zu frames, %zu lost\n",
              whole_ate, whole.trajectory.size(), sections, joined_ate, joined.size(), lost);
  EXPECT_EQ(sections, 4u);
  EXPECT_EQ(reinitialized, 0u) << "every section continues the one map";
  EXPECT_LE(lost, 2u * (sections - 1)) << "each section relocalizes within a frame or two";
  EXPECT_GE(joined.size(), dataset->size() - 2 * (sections - 1));
  // Same trajectory within tracking noise: the joined run is as accurate as the whole one.
  EXPECT_LT(joined_ate, std::max(1.5 * whole_ate, whole_ate + 0.01));
  std::filesystem::remove_all(dir);
}

TEST(ContinuedSession, LocalizationOnlyLeavesTheMapUnchanged) {
  const auto dataset = OpenDataset(kScene);
  SlamRunOptions first;
  first.max_frames = 300;
  std::vector<uint8_t> before;
  SnapshotMetadata metadata;
  metadata.calibration = dataset->calibration();
  first.on_finished = [&](const Slam& slam) {
    const SnapshotMapRef ref{0, &slam.map()};
    before = SerializeMapSnapshot({&ref, 1}, metadata);
  };
  (void)RunSlam(*dataset, Options(), first);
  LoadedSnapshot snapshot = LoadMapSnapshotFromBytes(before, "first session");
  Map map = std::move(snapshot.maps[0].map);

  SlamOptions options = Options();
  options.localization_only = true;
  SlamRunOptions run;
  run.first_frame = 100;  // a stretch the map covers
  run.max_frames = 300;
  run.initial_map = &map;
  std::vector<uint8_t> after;
  run.on_finished = [&](const Slam& slam) {
    const SnapshotMapRef ref{0, &slam.map()};
    after = SerializeMapSnapshot({&ref, 1}, metadata);
  };
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
