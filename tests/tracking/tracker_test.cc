// Tracking as a function that reads the map: a map made from one rendered RGB-D frame at its true
// pose, a later frame tracked against it. The map must come out bit for bit as it went in; the
// pose must match the renderer's; the sightings are what mapping then counts.
#include "tracking/tracker.h"

#include <algorithm>
#include <cmath>
#include <memory>
#include <vector>

#include <gtest/gtest.h>

#include "io/dataset.h"
#include "slam/session.h"

namespace flatslam {
namespace {

// Everything observable about a map that tracking could write: point positions, counters and
// observations, keyframe poses and points.
struct MapFingerprint {
  std::vector<double> numbers;
  static MapFingerprint Of(const Map& map) {
    MapFingerprint f;
    for (PointHandle p : map.points().handles()) {
      const MapPoint& point = map.point(p);
      f.numbers.insert(f.numbers.end(),
                       {point.position.x(), point.position.y(), point.position.z(), double(point.visible),
                        double(point.found), double(point.observations.size())});
    }
    for (const KeyFrame& kf : map.keyframes().values()) {
      const Eigen::Matrix4d T = kf.T_cam_world.matrix();
      f.numbers.insert(f.numbers.end(), T.data(), T.data() + 16);
      for (PointHandle p : kf.points) f.numbers.push_back(p.is_null() ? -1.0 : double(p.index()));
    }
    return f;
  }
};

class TrackerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dataset_ = OpenDataset("synth:room:duration=2,width=480,height=360,sensor=rgbd");
    options_.orb.features = 1000;
    session_ = std::make_unique<SlamSession>(dataset_->calibration(), options_);
    const SlamOptions resolved = ResolvedOptions(options_, dataset_->calibration());
    context_ = std::make_unique<SystemContext>(dataset_->calibration(), resolved, OrbExtractor(resolved.orb).scales());
    gt_ = *dataset_->ground_truth();
  }
  TrackedFrame Extract(size_t i) {
    TrackedFrame f;
    session_->Extract(dataset_->read(i), &f);
    return f;
  }
  Eigen::Isometry3d TrueCamWorld(size_t i) const { return gt_[i].T_world_cam.inverse(); }
  // The map: frame 0 at its true pose, every keypoint with depth a point; *first is that frame
  // with its point handles.
  KeyFrameHandle MapFrameZero(Map& map, TrackedFrame* first) {
    LocalMappingState mapping;
    *first = Extract(0);
    first->T_cam_world = TrueCamWorld(0);
    return InsertKeyFrame(map, mapping, *context_, *first, /*all_depth_points=*/true);
  }

  std::unique_ptr<Dataset> dataset_;
  SlamOptions options_;
  std::unique_ptr<SlamSession> session_;
  std::unique_ptr<SystemContext> context_;
  Trajectory gt_;
};

TEST_F(TrackerTest, TracksAFrameAgainstAMapItDoesNotChange) {
  Map map;
  TrackedFrame first;
  const KeyFrameHandle kf = MapFrameZero(map, &first);
  ASSERT_GT(map.points().size(), 300u);

  TrackerState state;
  state.state = TrackingState::kOk;
  state.reference_keyframe = state.first_keyframe = kf;
  state.segment_keyframes = 1;
  state.last_frame = first;  // no velocity yet: the reference-keyframe search runs

  const KeyFrameDatabase database(0);
  const size_t later = 4;
  TrackedFrame frame = Extract(later);
  const MapFingerprint before = MapFingerprint::Of(map);
  TrackResult result = TrackFrame(map, database, *context_, state, frame, /*pending_keyframes=*/0);
  EXPECT_EQ(MapFingerprint::Of(map).numbers, before.numbers) << "tracking wrote the map";

  ASSERT_TRUE(result.ok);
  const Eigen::Isometry3d error = frame.T_cam_world * TrueCamWorld(later).inverse();
  EXPECT_LT(error.translation().norm(), 0.01);
  EXPECT_LT(Eigen::AngleAxisd(error.linear()).angle(), 0.2 * M_PI / 180);
  EXPECT_EQ(state.reference_keyframe, kf);

  // Sightings: every matched point was predicted in view; each is one of the frame's points.
  ASSERT_GT(result.found.size(), 100u);
  EXPECT_GE(result.visible.size(), result.found.size());
  for (PointHandle p : result.found)
    EXPECT_NE(std::find(frame.points.begin(), frame.points.end(), p), frame.points.end());

  // Mapping counts them: found and visible grow by one per sighting.
  ApplySightings(map, result.visible, result.found);
  for (PointHandle p : result.found) EXPECT_EQ(map.point(p).found, 2u);  // made by the keyframe: 1

  // The pose is recorded against the reference keyframe, and the frame becomes the last frame.
  std::optional<KeyFrameHandle> new_keyframe;
  const std::optional<AnchoredFramePose> pose =
      FinishFrame(map, state, std::move(frame), result, InsertedTwoView{}, &new_keyframe);
  ASSERT_TRUE(pose.has_value());
  EXPECT_EQ(pose->reference, kf);
  EXPECT_EQ(result.report.state, TrackingState::kOk);
  ASSERT_TRUE(state.last_frame.has_value());
  EXPECT_EQ(state.last_frame->index, later);
}

TEST_F(TrackerTest, AFrameWithoutMatchesIsLostAndTheMapStaysAsItWas) {
  Map map;
  TrackedFrame first;
  const KeyFrameHandle kf = MapFrameZero(map, &first);
  TrackerState state;
  state.state = TrackingState::kOk;
  state.reference_keyframe = state.first_keyframe = kf;
  state.last_frame = first;
  state.allow_new_segments = false;  // an adopted map: stay lost rather than start a segment

  // A frame whose keypoints match nothing: descriptors scrambled.
  TrackedFrame frame = Extract(1);
  for (Descriptor& d : frame.keypoints.descriptor)
    for (uint64_t& word : d) word = ~word;
  const MapFingerprint before = MapFingerprint::Of(map);
  const KeyFrameDatabase database(0);
  TrackResult result = TrackFrame(map, database, *context_, state, frame, 0);
  EXPECT_FALSE(result.ok);
  EXPECT_EQ(result.insert, TrackResult::Insert::kNone);
  EXPECT_EQ(state.state, TrackingState::kLost);
  EXPECT_EQ(MapFingerprint::Of(map).numbers, before.numbers);
}

// A resumed checkpoint: the last two frames' poses and reference keyframe are all the state there
// is; tracking goes on from their motion without relocalizing (there is no place index here).
TEST_F(TrackerTest, ResumesFromTheLastTwoPosesOfACheckpoint) {
  Map map;
  TrackedFrame first;
  const KeyFrameHandle kf = MapFrameZero(map, &first);
  auto record = [&](size_t i) {
    AnchoredFramePose pose;
    pose.t_ns = gt_[i].t_ns;
    pose.reference = kf;
    pose.T_cam_world = CompactPose(TrueCamWorld(i));
    pose.T_cam_ref = CompactPose(TrueCamWorld(i) * map.keyframe(kf).T_cam_world.inverse());
    return pose;
  };
  TrackerState state;
  state.state = TrackingState::kLost;  // how an adopted map starts
  state.allow_new_segments = false;
  ASSERT_TRUE(ResumeTracking(map, *context_, record(2), record(3), state));
  EXPECT_EQ(state.state, TrackingState::kOk);
  EXPECT_EQ(state.reference_keyframe, kf);
  ASSERT_TRUE(state.velocity.has_value());
  EXPECT_TRUE(state.velocity->isApprox(TrueCamWorld(3) * TrueCamWorld(2).inverse(), 1e-4));

  TrackedFrame frame = Extract(4);
  const KeyFrameDatabase database(0);
  const TrackResult result = TrackFrame(map, database, *context_, state, frame, 0);
  ASSERT_TRUE(result.ok);
  EXPECT_FALSE(result.report.relocalized);
  EXPECT_LT((frame.T_cam_world * TrueCamWorld(4).inverse()).translation().norm(), 0.01);

  // A reference keyframe that is gone: nothing to resume from, the state is left as it was.
  TrackerState lost;
  lost.state = TrackingState::kLost;
  AnchoredFramePose gone = record(3);
  gone.reference = KeyFrameHandle::null();
  EXPECT_FALSE(ResumeTracking(map, *context_, record(2), gone, lost));
  EXPECT_EQ(lost.state, TrackingState::kLost);
  EXPECT_FALSE(lost.velocity.has_value());
}

}  // namespace
}  // namespace flatslam
