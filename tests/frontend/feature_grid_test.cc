// The keypoint grid's radius queries against a scan of every keypoint, and a grid built over a
// subset of the keypoints against the full grid's answers filtered to that subset.
#include <algorithm>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "frontend/frame.h"

namespace flatslam {
namespace {

constexpr int kWidth = 1241, kHeight = 376;

std::vector<Eigen::Vector2f> RandomKeypoints(size_t n, uint32_t seed) {
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(0.0f, kWidth - 1.0f), v(0.0f, kHeight - 1.0f);
  std::vector<Eigen::Vector2f> uv(n);
  for (Eigen::Vector2f& p : uv) p = {u(rng), v(rng)};
  // Points on cell borders and image corners, where rounding decides the cell.
  uv.push_back({0.0f, 0.0f});
  uv.push_back({24.0f, 48.0f});
  uv.push_back({kWidth - 1.0f, kHeight - 1.0f});
  return uv;
}

std::vector<uint32_t> Sorted(std::vector<uint32_t> v) {
  std::sort(v.begin(), v.end());
  return v;
}

TEST(FeatureGrid, QueryFindsExactlyTheKeypointsInTheSquare) {
  const std::vector<Eigen::Vector2f> uv = RandomKeypoints(2000, 1);
  FeatureGrid grid;
  grid.Build(uv, kWidth, kHeight);
  std::mt19937 rng(2);
  std::uniform_real_distribution<float> u(-50.0f, kWidth + 50.0f), v(-50.0f, kHeight + 50.0f), r(0.5f, 80.0f);
  for (int q = 0; q < 300; ++q) {
    const float qu = u(rng), qv = v(rng), qr = r(rng);
    // Query appends: what the vector held stays in front.
    constexpr uint32_t kHeld = 123456;
    std::vector<uint32_t> found = {kHeld};
    grid.Query(qu, qv, qr, &found);
    ASSERT_EQ(found.front(), kHeld);
    found.erase(found.begin());
    std::vector<uint32_t> expected;
    for (uint32_t i = 0; i < uv.size(); ++i)
      if (std::abs(uv[i].x() - qu) <= qr && std::abs(uv[i].y() - qv) <= qr) expected.push_back(i);
    ASSERT_EQ(Sorted(found), expected) << "query (" << qu << ", " << qv << ") r " << qr;
  }
}

TEST(FeatureGrid, AGridOverSomeKeypointsAnswersAsTheFullGridFilteredToThem) {
  const std::vector<Eigen::Vector2f> uv = RandomKeypoints(2000, 3);
  std::vector<uint8_t> keep(uv.size());
  for (size_t i = 0; i < uv.size(); ++i) keep[i] = (i * 7919) % 3 != 0;  // about two in three
  FeatureGrid full, some;
  full.Build(uv, kWidth, kHeight);
  some.BuildWhere(uv, kWidth, kHeight, [&](size_t i) { return keep[i] != 0; });
  std::mt19937 rng(4);
  std::uniform_real_distribution<float> u(0.0f, kWidth), v(0.0f, kHeight), r(1.0f, 60.0f);
  size_t answers = 0;
  for (int q = 0; q < 300; ++q) {
    const float qu = u(rng), qv = v(rng), qr = r(rng);
    std::vector<uint32_t> from_full, from_some;
    full.Query(qu, qv, qr, &from_full);
    some.Query(qu, qv, qr, &from_some);
    std::erase_if(from_full, [&](uint32_t i) { return keep[i] == 0; });
    // The same keypoints in the same order: matching breaks ties by the order of candidates.
    ASSERT_EQ(from_some, from_full) << "query (" << qu << ", " << qv << ") r " << qr;
    answers += from_some.size();
  }
  EXPECT_GT(answers, 1000u);  // the queries do find keypoints
  // Reused for a different subset, the grid forgets the last one.
  some.BuildWhere(uv, kWidth, kHeight, [](size_t i) { return i == 5; });
  std::vector<uint32_t> found;
  some.Query(uv[5].x(), uv[5].y(), 1.0f, &found);
  EXPECT_EQ(found, std::vector<uint32_t>{5});
  found.clear();
  some.Query(kWidth / 2.0f, kHeight / 2.0f, 2000.0f, &found);
  EXPECT_EQ(found, std::vector<uint32_t>{5});
}

}  // namespace
}  // namespace flatslam
