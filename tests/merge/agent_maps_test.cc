// The map server's maps of live agents, grown from keyframe messages.
#include "merge/agent_maps.h"

#include <gtest/gtest.h>

#include "storage/keyframe_message.h"
#include "storage/random_map.h"

namespace flatslam {
namespace {

// The server's maps: keyframes join their points by the agent's ids, a keyframe sent again updates
// what is there (the agent's final map), and a restarted agent (a new session) gets a map of its own.
TEST(AgentMaps, JoinPointsAcrossKeyFramesAndKeepSessionsApart) {
  testing::RandomMapOptions o;
  o.erase_some = false;
  o.agents = 1;
  const Map map = testing::RandomMap(o);
  AgentMaps maps;
  for (KeyFrameHandle h : map.keyframes().handles())
    EXPECT_TRUE(maps.Add(DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, h, 0, 11, testing::TestAgentCamera()), "m")));
  // A keyframe sent twice is applied once.
  EXPECT_FALSE(maps.Add(DecodeKeyFrameMessage(
      EncodeKeyFrameMessage(map, map.keyframes().handles()[0], 0, 11, testing::TestAgentCamera()), "repeated")));
  ASSERT_EQ(maps.sessions().size(), 1u);
  const Map& got = maps.sessions()[0].map;
  EXPECT_EQ(got.keyframes().size(), map.keyframes().size());
  size_t observed = 0, observations = 0;
  for (const MapPoint& p : map.points().values()) {
    observed += !p.observations.empty();
    observations += p.observations.size();
  }
  EXPECT_EQ(got.points().size(), observed);
  size_t got_observations = 0;
  for (const MapPoint& p : got.points().values()) got_observations += p.observations.size();
  EXPECT_EQ(got_observations, observations);
  EXPECT_EQ(got.Validate(), "");
  // The agent's final update: a keyframe moved by a loop correction, a point culled. The server's
  // map follows: same keyframes, the point gone, the pose moved.
  Map changed = map;
  const KeyFrameHandle first = changed.keyframes().handles()[0];
  changed.keyframe(first).T_cam_world.translation() += Eigen::Vector3d(0.5, 0, 0);
  PointHandle culled;
  for (PointHandle p : changed.keyframe(first).points)
    if (!p.is_null()) culled = p;
  ASSERT_FALSE(culled.is_null());
  changed.ErasePoint(culled);
  for (KeyFrameHandle h : changed.keyframes().handles())
    EXPECT_FALSE(maps.Add(
        DecodeKeyFrameMessage(EncodeKeyFrameMessage(changed, h, 0, 11, testing::TestAgentCamera()), "update")));
  const Map& updated = maps.sessions()[0].map;
  EXPECT_EQ(updated.keyframes().size(), map.keyframes().size());
  EXPECT_EQ(updated.points().size(), observed - 1);
  EXPECT_EQ(updated.Validate(), "");
  bool moved = false;
  for (const KeyFrame& kf : updated.keyframes().values())
    moved = moved || kf.T_cam_world.isApprox(changed.keyframe(first).T_cam_world, 1e-12);
  EXPECT_TRUE(moved);
  // The same agent restarted: a second map.
  EXPECT_TRUE(maps.Add(DecodeKeyFrameMessage(
      EncodeKeyFrameMessage(map, map.keyframes().handles()[0], 0, 12, testing::TestAgentCamera()), "restarted")));
  EXPECT_EQ(maps.sessions().size(), 2u);
  ASSERT_TRUE(maps.camera().has_value());
  EXPECT_EQ(maps.camera()->calibration.camera.width, 640);
}

}  // namespace
}  // namespace flatslam
