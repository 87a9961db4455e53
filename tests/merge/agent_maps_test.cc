// The map server's maps of live agents, grown from keyframe messages.
#include "merge/agent_maps.h"

#include <iterator>
#include <map>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "storage/keyframe_message.h"
#include "storage/random_map.h"

namespace flatslam {
namespace {

// A random map of one agent, nothing erased: every point keeps all its observations.
Map OneAgentMap() {
  testing::RandomMapOptions o;
  o.erase_some = false;
  o.agents = 1;
  return testing::RandomMap(o);
}

// Every keyframe of `map` as agent 0's run 11 sends it (each one new to the server).
void SendEveryKeyFrame(const Map& map, AgentMaps* maps) {
  for (KeyFrameHandle h : map.keyframes().handles())
    EXPECT_TRUE(
        maps->Add(DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, h, 0, 11, testing::TestAgentCamera()), "m")));
}

// The server's maps: keyframes join their points by the agent's ids, a keyframe sent again updates
// what is there (the agent's final map), and a restarted agent (a new session) gets a map of its own.
TEST(AgentMaps, JoinPointsAcrossKeyFramesAndKeepSessionsApart) {
  const Map map = OneAgentMap();
  AgentMaps maps;
  SendEveryKeyFrame(map, &maps);
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
  // Points arrive as positions; the server computes viewing direction and representative
  // descriptor from the observations it holds, as the agent does from the same ones.
  maps.RefreshPointStats();
  Map expected = map;
  for (PointHandle p : expected.points().handles()) expected.UpdatePointStats(p, testing::TestAgentCamera().scales);
  std::map<int64_t, KeyFrameHandle> by_time;
  for (KeyFrameHandle h : expected.keyframes().handles()) by_time[expected.keyframe(h).t_ns] = h;
  size_t compared = 0;
  for (const KeyFrame& kf : got.keyframes().values()) {
    const KeyFrame& agent_kf = expected.keyframe(by_time.at(kf.t_ns));
    for (size_t k = 0; k < kf.size(); ++k) {
      if (kf.points[k].is_null()) continue;
      const MapPoint& server_point = got.point(kf.points[k]);
      const MapPoint& agent_point = expected.point(agent_kf.points[k]);
      EXPECT_EQ(server_point.descriptor, agent_point.descriptor);
      EXPECT_TRUE(server_point.normal.isApprox(agent_point.normal, 1e-5));
      EXPECT_LT((server_point.position - agent_point.position).norm(), 1e-4);
      ++compared;
    }
  }
  EXPECT_EQ(compared, observations);
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

// Keyframes the agent culled leave the server's map too, with the points only they saw; ids it
// does not hold and other runs are left alone.
TEST(AgentMaps, CulledKeyFramesLeaveTheMap) {
  const Map map = OneAgentMap();
  AgentMaps maps;
  SendEveryKeyFrame(map, &maps);
  const size_t keyframes = map.keyframes().size(), points = maps.sessions()[0].map.points().size();
  KeyFramesCulled culled;
  culled.agent = 0;
  culled.session = 11;
  for (size_t i : {3, 4, 5, 6}) culled.keyframes.push_back(map.keyframes().values()[i].id);
  culled.keyframes.push_back(999999);  // never sent
  EXPECT_EQ(maps.Cull(DecodeKeyFramesCulled(EncodeKeyFramesCulled(culled), "culled")), 4u);
  const Map& got = maps.sessions()[0].map;
  EXPECT_EQ(got.keyframes().size(), keyframes - 4);
  EXPECT_LT(got.points().size(), points);  // points seen by those four alone went with them
  for (const MapPoint& p : got.points().values()) EXPECT_FALSE(p.observations.empty());
  for (const KeyFrame& kf : got.keyframes().values())
    for (uint64_t id : culled.keyframes) EXPECT_NE(kf.id, id);
  EXPECT_EQ(got.Validate(), "");
  // Again, or for another run: nothing to do.
  EXPECT_EQ(maps.Cull(culled), 0u);
  culled.session = 12;
  EXPECT_EQ(maps.Cull(culled), 0u);
}

// A run resumed from its checkpoint replaces the run it continues: the server drops that run's map
// and keeps every other run's, whose messages still land in their own maps.
TEST(AgentMaps, ADroppedRunLeavesTheOthersWhereTheyWere) {
  const Map map = OneAgentMap();
  AgentMaps maps;
  const KeyFrameHandle first = map.keyframes().handles().front();
  for (uint64_t session : {11, 12, 13})
    EXPECT_TRUE(maps.Add(
        DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, first, 0, session, testing::TestAgentCamera()), "m")));
  ASSERT_EQ(maps.sessions().size(), 3u);
  EXPECT_EQ(maps.Drop(0, 12), 1u);
  EXPECT_EQ(maps.Drop(0, 12), 0u);  // gone already
  EXPECT_EQ(maps.Drop(1, 11), 0u);  // another agent's run of that id was never heard of
  ASSERT_EQ(maps.sessions().size(), 2u);
  EXPECT_EQ(maps.sessions()[0].session, 11u);
  EXPECT_EQ(maps.sessions()[1].session, 13u);
  // Run 13's next keyframe joins run 13's map (its index moved down by one).
  const KeyFrameHandle second = map.keyframes().handles()[1];
  EXPECT_TRUE(
      maps.Add(DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, second, 0, 13, testing::TestAgentCamera()), "m")));
  EXPECT_EQ(maps.sessions()[0].map.keyframes().size(), 1u);
  EXPECT_EQ(maps.sessions()[1].map.keyframes().size(), 2u);
  // The dropped run, heard again, starts over with a map of its own.
  EXPECT_TRUE(
      maps.Add(DecodeKeyFrameMessage(EncodeKeyFrameMessage(map, first, 0, 12, testing::TestAgentCamera()), "m")));
  EXPECT_EQ(maps.sessions().size(), 3u);
}

// Corrections: each input's frame in the output map that holds it, fitted on its keyframes found
// there by agent and timestamp. An input that stays alone gets none.
TEST(AgentMaps, RunFramesRecoverWhereEachInputWentInTheMergedMap) {
  testing::RandomMapOptions o;
  o.erase_some = false;
  o.agents = 1;
  Map a = testing::RandomMap(o);
  o.seed = 8;
  Map b = testing::RandomMap(o);
  for (KeyFrameHandle h : b.keyframes().handles()) b.keyframe(h).agent = 1;
  Map c = testing::RandomMap(o);
  for (KeyFrameHandle h : c.keyframes().handles()) c.keyframe(h).agent = 2;
  const std::vector<KeyFramePoses> centres = {PosesOf(a), PosesOf(b), PosesOf(c)};
  const std::vector<uint32_t> agents = {0, 1, 2};
  Similarity3 S;
  S.R = Eigen::AngleAxisd(0.4, Eigen::Vector3d::UnitY()).toRotationMatrix();
  S.t = Eigen::Vector3d(3, 0.5, -1);
  S.s = 1.7;
  MultiMapMerge merged;
  merged.maps.push_back(a);
  (void)AppendMap(merged.maps[0], b, S);
  merged.maps.push_back(c);
  merged.members = {{0, 1}, {2}};
  const auto frames = FitRunFrames(merged, agents, centres, /*fix_scale=*/false);
  ASSERT_EQ(frames.size(), 3u);
  ASSERT_TRUE(frames[0] && frames[1]);
  EXPECT_FALSE(frames[2]) << "alone in its own map: no correction";
  EXPECT_EQ(frames[0]->output, 0u);
  EXPECT_EQ(frames[0]->keyframes, a.keyframes().size());
  EXPECT_TRUE(frames[0]->S_output_input.R.isApprox(Eigen::Matrix3d::Identity(), 1e-9));
  EXPECT_LT(frames[0]->S_output_input.t.norm(), 1e-9);
  EXPECT_NEAR(frames[0]->S_output_input.s, 1.0, 1e-9);
  EXPECT_EQ(frames[1]->keyframes, b.keyframes().size());
  EXPECT_TRUE(frames[1]->S_output_input.R.isApprox(S.R, 1e-9));
  EXPECT_TRUE(frames[1]->S_output_input.t.isApprox(S.t, 1e-9));
  EXPECT_NEAR(frames[1]->S_output_input.s, 1.7, 1e-9);
  EXPECT_LT(frames[1]->rms, 1e-9);
  // Stereo: the rigid part only (scale held at 1).
  const auto rigid = FitRunFrames(merged, agents, centres, /*fix_scale=*/true);
  ASSERT_TRUE(rigid[1]);
  EXPECT_EQ(rigid[1]->S_output_input.s, 1.0);
  EXPECT_TRUE(rigid[1]->S_output_input.R.isApprox(S.R, 1e-6));
  // Two runs of one agent in one map with the same frames: their keyframes are ambiguous and no
  // run gets a fit from them.
  // The newest keyframes moved again (the merged map corrected drift there): a fit on the newest
  // follows them.
  const Eigen::Isometry3d D(Eigen::Translation3d(0.3, -0.2, 0.1) * Eigen::AngleAxisd(0.05, Eigen::Vector3d::UnitZ()));
  const int64_t newest_five = std::prev(centres[1].end(), 5)->first;
  for (KeyFrameHandle h : merged.maps[0].keyframes().handles()) {
    KeyFrame& kf = merged.maps[0].keyframe(h);
    if (kf.agent == 1 && kf.t_ns >= newest_five) kf.T_cam_world = kf.T_cam_world * D.inverse();
  }
  const auto recent = FitRunFrames(merged, agents, centres, /*fix_scale=*/false, 5);
  ASSERT_TRUE(recent[1]);
  EXPECT_EQ(recent[1]->keyframes, 5u);
  const Similarity3 expected = Similarity3::FromIsometry(D) * S;
  EXPECT_TRUE(recent[1]->S_output_input.R.isApprox(expected.R, 1e-9));
  EXPECT_TRUE(recent[1]->S_output_input.t.isApprox(expected.t, 1e-9));
  EXPECT_NEAR(recent[1]->S_output_input.s, 1.7, 1e-9);
  const auto all = FitRunFrames(merged, agents, centres, /*fix_scale=*/false);
  EXPECT_GT(all[1]->rms, 0.01) << "the whole run no longer fits one similarity";

  Map b0 = b;
  for (KeyFrameHandle h : b0.keyframes().handles()) b0.keyframe(h).agent = 0;
  MultiMapMerge restarted;
  restarted.maps.push_back(a);
  (void)AppendMap(restarted.maps[0], b0, S);
  restarted.members = {{0, 1}};
  const auto ambiguous = FitRunFrames(restarted, {0, 0}, {centres[0], centres[1]}, false);
  EXPECT_FALSE(ambiguous[0]);
  EXPECT_FALSE(ambiguous[1]);
}

}  // namespace
}  // namespace flatslam
