#include "storage/keyframe_message.h"

#include <string>
#include <unordered_set>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "core/error.h"
#include "storage/random_map.h"

namespace flatslam {
namespace {

std::string KeyFrameMessageErrorOf(std::span<const uint8_t> bytes) {
  try {
    (void)DecodeKeyFrameMessage(bytes, "message 7 from agent 3");
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

// A keyframe goes out with its camera and the points it sees, and comes back the same.
TEST(KeyFrameMessage, RoundTripsAKeyFrameWithItsPoints) {
  const Map map = testing::RandomMap({});
  const KeyFrameHandle h = map.keyframes().handles()[5];
  const KeyFrame& kf = map.keyframe(h);
  const std::vector<uint8_t> bytes = EncodeKeyFrameMessage(map, h, 3, 0xabcdef, testing::TestAgentCamera());
  const KeyFrameMessage m = DecodeKeyFrameMessage(bytes, "test");
  EXPECT_EQ(m.agent, 3u);
  EXPECT_EQ(m.session, 0xabcdefu);
  EXPECT_EQ(m.camera.calibration.camera.width, 640);
  EXPECT_DOUBLE_EQ(m.camera.calibration.baseline_m, 0.12);
  EXPECT_EQ(m.camera.scales.levels, 8);
  EXPECT_EQ(m.keyframe.id, kf.id);
  EXPECT_EQ(m.keyframe.t_ns, kf.t_ns);
  EXPECT_TRUE(m.keyframe.T_cam_world.isApprox(kf.T_cam_world, 1e-12));
  EXPECT_EQ(m.keyframe.uv, kf.uv);
  EXPECT_EQ(m.keyframe.descriptor, kf.descriptor);
  EXPECT_EQ(m.keyframe.depth, kf.depth);
  ASSERT_EQ(m.keypoint_point.size(), kf.size());
  size_t bound = 0;
  for (size_t k = 0; k < kf.size(); ++k) {
    if (kf.points[k].is_null()) {
      EXPECT_EQ(m.keypoint_point[k], KeyFrameMessage::kNoPoint);
      continue;
    }
    ++bound;
    const uint32_t i = m.keypoint_point[k];
    ASSERT_LT(i, m.positions.size());
    EXPECT_EQ(m.point_ids[i], kf.points[k].packed());
    // Single precision in the camera frame: within 1e-6 of the point's distance from the camera.
    const Eigen::Vector3d& X = map.point(kf.points[k]).position;
    const double distance = (X - kf.camera_center()).norm();
    EXPECT_LT((m.positions[i] - X).norm(), 1e-6 * distance) << k;
  }
  EXPECT_GT(bound, 0u);
}

// A point costs its id and three floats: 20 bytes, plus a few for the vectors' alignment.
TEST(KeyFrameMessage, APointCostsItsIdAndItsPosition) {
  const Map map = testing::RandomMap({});
  const KeyFrameHandle h = map.keyframes().handles()[5];
  KeyFrame bare = map.keyframe(h);
  size_t points = 0;
  {
    std::unordered_set<PointHandle> seen;
    for (PointHandle p : bare.points)
      if (map.points().contains(p)) seen.insert(p);
    points = seen.size();
  }
  ASSERT_GT(points, 20u);
  // The same keyframe seeing no points: the difference is what its points cost.
  Map without = map;
  for (PointHandle p : map.keyframe(h).points)
    if (!p.is_null() && without.points().contains(p)) without.EraseObservation(p, h, /*min_observations=*/0);
  const size_t with_points = EncodeKeyFrameMessage(map, h, 3, 1, testing::TestAgentCamera()).size();
  const size_t without_points = EncodeKeyFrameMessage(without, h, 3, 1, testing::TestAgentCamera()).size();
  EXPECT_LE(with_points - without_points, points * 20 + 32);
}

// An agent whose map moved into a merged map's frame sends in its run's own frame: the pose and
// the points come out moved back, everything else as it is.
TEST(KeyFrameMessage, IsWrittenInTheFrameAsked) {
  const Map map = testing::RandomMap({});
  const KeyFrameHandle h = map.keyframes().handles()[5];
  const KeyFrame& kf = map.keyframe(h);
  Eigen::Isometry3d T_out_map = Eigen::Isometry3d::Identity();
  T_out_map.linear() = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  T_out_map.translation() = Eigen::Vector3d(-4, 1, 9);
  const KeyFrameMessage m =
      DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, h, 3, 1, testing::TestAgentCamera(), T_out_map), "moved");
  const KeyFrameMessage plain =
      DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, h, 3, 1, testing::TestAgentCamera()), "plain");
  // The camera sees every point where it saw it: camera-frame coordinates are unchanged.
  EXPECT_TRUE(m.keyframe.T_cam_world.isApprox(kf.T_cam_world * T_out_map.inverse(), 1e-12));
  EXPECT_EQ(m.keyframe.uv, kf.uv);
  ASSERT_EQ(m.positions.size(), plain.positions.size());
  ASSERT_GT(m.positions.size(), 0u);
  for (size_t i = 0; i < m.positions.size(); ++i) {
    EXPECT_EQ(m.point_ids[i], plain.point_ids[i]);
    EXPECT_TRUE(m.positions[i].isApprox(T_out_map * plain.positions[i], 1e-9));
    EXPECT_TRUE(
        (m.keyframe.T_cam_world * m.positions[i]).isApprox(plain.keyframe.T_cam_world * plain.positions[i], 1e-9));
  }
}

// Whatever arrives, decoding either returns a verified message or throws naming the message.
TEST(KeyFrameMessage, MalformedMessagesAreRefusedWithTheirName) {
  const Map map = testing::RandomMap({});
  const std::vector<uint8_t> bytes =
      EncodeKeyFrameMessage(map, map.keyframes().handles()[2], 1, 1, testing::TestAgentCamera());
  EXPECT_NE(KeyFrameMessageErrorOf({}).find("message 7 from agent 3: not a keyframe message"), std::string::npos);
  std::vector<uint8_t> other = bytes;
  other[4] = 'X';  // another file identifier
  EXPECT_NE(KeyFrameMessageErrorOf(other).find("not a keyframe message"), std::string::npos);
  // Every truncation is refused (or, where only padding is cut, decodes whole).
  for (size_t n = 0; n < bytes.size(); n += 97) {
    const std::string error = KeyFrameMessageErrorOf(std::span(bytes).first(n));
    EXPECT_NE(error.find("message 7 from agent 3"), std::string::npos) << n;
  }
  // Flipped bytes anywhere: never a crash; an error names the message.
  std::mt19937_64 rng(5);
  size_t refused = 0;
  for (int trial = 0; trial < 300; ++trial) {
    std::vector<uint8_t> bad = bytes;
    bad[rng() % bad.size()] ^= static_cast<uint8_t>(1 + rng() % 255);
    const std::string error = KeyFrameMessageErrorOf(bad);
    if (!error.empty()) {
      ++refused;
      EXPECT_NE(error.find("message 7 from agent 3"), std::string::npos) << error;
    }
  }
  EXPECT_GT(refused, 0u);
}

TEST(KeyFramesCulled, RoundTripsAndRefusesWhatIsNotOne) {
  KeyFramesCulled culled;
  culled.agent = 4;
  culled.session = 0xfeedULL;
  culled.keyframes = {3, 17, 1ull << 40};
  const std::vector<uint8_t> bytes = EncodeKeyFramesCulled(culled);
  const KeyFramesCulled back = DecodeKeyFramesCulled(bytes, "culled 2 from agent 4");
  EXPECT_EQ(back.agent, 4u);
  EXPECT_EQ(back.session, 0xfeedULL);
  EXPECT_EQ(back.keyframes, culled.keyframes);
  auto error_of = [](std::span<const uint8_t> b) {
    try {
      (void)DecodeKeyFramesCulled(b, "culled 2 from agent 4");
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  // A keyframe message is not a culled-keyframes message, and no truncation decodes.
  const Map map = testing::RandomMap({});
  EXPECT_NE(error_of(EncodeKeyFrameMessage(map, map.keyframes().handles()[0], 1, 1, testing::TestAgentCamera()))
                .find("culled 2 from agent 4: not a culled-keyframes message"),
            std::string::npos);
  for (size_t n = 0; n < bytes.size(); n += 5)
    EXPECT_NE(error_of(std::span(bytes).first(n)).find("culled 2 from agent 4"), std::string::npos) << n;
}

TEST(RunEnded, RoundTripsAndRefusesWhatIsNotOne) {
  RunEnded ended;
  ended.agent = 2;
  ended.session = 0xabcdef0123ULL;
  ended.keyframes = 91;
  ended.frames = 1200;
  ended.stopped = true;
  ended.resumed_by = 0x1234567890ULL;
  const std::vector<uint8_t> bytes = EncodeRunEnded(ended);
  const RunEnded back = DecodeRunEnded(bytes, "keyframe message 7 from agent 2");
  EXPECT_EQ(back.agent, 2u);
  EXPECT_EQ(back.session, ended.session);
  EXPECT_EQ(back.keyframes, 91u);
  EXPECT_EQ(back.frames, 1200u);
  EXPECT_TRUE(back.stopped);
  EXPECT_EQ(back.resumed_by, ended.resumed_by);
  ended.stopped = false;
  ended.resumed_by = 0;
  EXPECT_FALSE(DecodeRunEnded(EncodeRunEnded(ended), "again").stopped);
  EXPECT_EQ(DecodeRunEnded(EncodeRunEnded(ended), "again").resumed_by, 0u);
  auto error_of = [](std::span<const uint8_t> b) {
    try {
      (void)DecodeRunEnded(b, "keyframe message 7 from agent 2");
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  // A culled-keyframes message is not a run-ended one, and no truncation decodes.
  KeyFramesCulled culled;
  culled.keyframes = {1};
  EXPECT_NE(error_of(EncodeKeyFramesCulled(culled)).find("keyframe message 7 from agent 2: not a run-ended message"),
            std::string::npos);
  for (size_t n = 0; n < bytes.size(); n += 3)
    EXPECT_NE(error_of(std::span(bytes).first(n)).find("keyframe message 7 from agent 2"), std::string::npos) << n;
}

}  // namespace
}  // namespace flatslam
