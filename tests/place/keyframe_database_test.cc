// Keyframe database: inverted index upkeep and candidate ranking on a hand-computed example.
#include "place/keyframe_database.h"

#include <algorithm>

#include <gtest/gtest.h>

#include "place/vocabulary.h"

namespace flatslam {
namespace {

KeyFrameHandle AddKeyFrame(Map& map, BowVector bow, size_t keypoints = 4) {
  KeyFrame kf;
  kf.resize(keypoints);
  kf.bow = std::move(bow);
  return map.AddKeyFrame(std::move(kf));
}

// Makes a and b covisible through `shared` common points.
void Link(Map& map, KeyFrameHandle a, KeyFrameHandle b, uint32_t shared) {
  uint32_t ka = 0, kb = 0;
  while (ka < map.keyframe(a).size() && !map.keyframe(a).points[ka].is_null()) ++ka;
  while (kb < map.keyframe(b).size() && !map.keyframe(b).points[kb].is_null()) ++kb;
  for (uint32_t k = 0; k < shared; ++k) {
    const PointHandle p = map.AddPoint(Eigen::Vector3d::Zero(), a);
    map.AddObservation(p, a, ka + k);
    map.AddObservation(p, b, kb + k);
  }
  map.UpdateCovisibility(a, 1);
  map.UpdateCovisibility(b, 1);
}

TEST(BowScoreTest, HandComputedL1Scores) {
  const BowVector a = {{1, 0.5f}, {2, 0.5f}};
  const BowVector b = {{2, 0.5f}, {3, 0.5f}};
  const BowVector c = {{2, 0.25f}, {5, 0.75f}};
  EXPECT_FLOAT_EQ(Vocabulary::Score(a, a), 1.0f);
  EXPECT_FLOAT_EQ(Vocabulary::Score(a, b), 0.5f);   // 1 - (0.5 + 0 + 0.5) / 2
  EXPECT_FLOAT_EQ(Vocabulary::Score(a, c), 0.25f);  // 1 - (0.5 + 0.25 + 0.75) / 2
  EXPECT_FLOAT_EQ(Vocabulary::Score(a, {{7, 1.0f}}), 0.0f);
}

class KeyFrameDatabaseTest : public ::testing::Test {
 protected:
  void SetUp() override {
    kf0 = AddKeyFrame(map, {{1, 0.5f}, {2, 0.5f}});    // score 1 against the query
    kf1 = AddKeyFrame(map, {{1, 0.5f}, {3, 0.5f}});    // 0.5
    kf2 = AddKeyFrame(map, {{4, 1.0f}});               // no common word
    kf3 = AddKeyFrame(map, {{2, 0.25f}, {5, 0.75f}});  // 0.25
    for (KeyFrameHandle h : {kf0, kf1, kf2, kf3}) db.Add(h, map.keyframe(h).bow);
  }
  Map map;
  KeyFrameDatabase db{8};
  KeyFrameHandle kf0, kf1, kf2, kf3;
  const BowVector query = {{1, 0.5f}, {2, 0.5f}};
};

TEST_F(KeyFrameDatabaseTest, InvertedIndexFollowsAddAndErase) {
  EXPECT_EQ(db.size(), 4u);
  EXPECT_EQ(db.keyframes_with(2), (std::vector<KeyFrameHandle>{kf0, kf3}));
  db.Erase(kf0, map.keyframe(kf0).bow);
  EXPECT_EQ(db.size(), 3u);
  EXPECT_EQ(db.keyframes_with(2), (std::vector<KeyFrameHandle>{kf3}));
  EXPECT_TRUE(db.keyframes_with(1) == std::vector<KeyFrameHandle>{kf1});
  EXPECT_THROW(db.Add(kf0, {{8, 1.0f}}), Error);  // word outside the vocabulary
  const KeyFrameHandle never_added = AddKeyFrame(map, {});
  db.Erase(never_added, {});
  EXPECT_EQ(db.size(), 3u);
  db.Add(kf1, map.keyframe(kf1).bow);  // already there: indexed once
  EXPECT_EQ(db.keyframes_with(1).size(), 1u);
}

TEST_F(KeyFrameDatabaseTest, UngroupedCandidatesKeepOnlyTheBestGroup) {
  // Groups are single keyframes: scores 1, 0.5, 0.25; only those within 75% of the best remain.
  const auto c = db.DetectRelocalizationCandidates(map, query);
  ASSERT_EQ(c.size(), 1u);
  EXPECT_EQ(c[0].keyframe, kf0);
  EXPECT_FLOAT_EQ(c[0].score, 1.0f);
}

TEST_F(KeyFrameDatabaseTest, CovisibleCandidatesAccumulate) {
  Link(map, kf1, kf3, 2);  // kf1 and kf3 now form a group worth 0.5 + 0.25
  const auto c = db.DetectRelocalizationCandidates(map, query);
  ASSERT_EQ(c.size(), 2u);
  EXPECT_EQ(c[0].keyframe, kf0);
  EXPECT_FLOAT_EQ(c[0].group_score, 1.0f);
  EXPECT_EQ(c[1].keyframe, kf1);  // the best of its group
  EXPECT_FLOAT_EQ(c[1].group_score, 0.75f);
}

TEST_F(KeyFrameDatabaseTest, LoopCandidatesExcludeNeighboursAndLowScores) {
  const KeyFrameHandle current = AddKeyFrame(map, query);
  Link(map, current, kf0, 1);  // kf0 is a neighbour: not a loop
  auto c = db.DetectLoopCandidates(map, current, 0.3f);
  ASSERT_EQ(c.size(), 1u);
  EXPECT_EQ(c[0].keyframe, kf1);
  EXPECT_TRUE(db.DetectLoopCandidates(map, current, 0.6f).empty());
}

}  // namespace
}  // namespace flatslam
