// Local mapping's steps on small hand-built maps: sightings, keyframe insertion with depth
// points, monocular triangulation's parallax floors, keyframe culling.
#include "mapping/local_mapping.h"

#include <algorithm>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "frontend/orb_extractor.h"

namespace flatslam {
namespace {

SystemContext MakeContext(Sensor sensor) {
  Calibration calibration;
  calibration.sensor = sensor;
  calibration.camera = {500, 500, 320, 240, 640, 480};
  calibration.frame_rate_hz = 20;
  SlamOptions options;
  options.orb.features = 1000;
  const SlamOptions resolved = ResolvedOptions(options, calibration);
  return SystemContext(calibration, resolved, OrbExtractor(resolved.orb).scales());
}

// A keyframe of n keypoints on a grid, at the origin.
KeyFrame GridKeyFrame(size_t n) {
  KeyFrame kf;
  kf.resize(n);
  Eigen::Vector2f* uv = kf.uv.mutable_data();
  Descriptor* descriptor = kf.descriptor.mutable_data();
  for (size_t i = 0; i < n; ++i) {
    uv[i] = Eigen::Vector2f(20.0f + 20.0f * (i % 30), 20.0f + 20.0f * (i / 30));
    descriptor[i] = Descriptor{i, 0, 0, 0};
  }
  return kf;
}

TEST(LocalMapping, SightingsCountOncePerFrameAndSkipErasedPoints) {
  Map map;
  const KeyFrameHandle kf = map.AddKeyFrame(GridKeyFrame(2));
  const PointHandle a = map.AddPoint({0, 0, 1}, kf), b = map.AddPoint({0, 0, 2}, kf);
  map.ErasePoint(b);
  const PointHandle seen[] = {a, b};
  ApplySightings(map, seen, std::span<const PointHandle>(seen, 1));
  EXPECT_EQ(map.point(a).visible, 2u);
  EXPECT_EQ(map.point(a).found, 2u);
}

TEST(LocalMapping, AKeyFrameGetsItsCloseDepthPointsAndAtLeastTheHundredNearest) {
  const SystemContext context = MakeContext(Sensor::kRgbd);
  const double close = context.CloseDepth();  // 35 x the 8 cm virtual baseline: 2.8 m
  ASSERT_NEAR(close, 2.8, 1e-9);
  TrackedFrame frame;
  frame.keypoints.resize(200);
  for (size_t i = 0; i < 200; ++i) {
    frame.keypoints.uv[i] = Eigen::Vector2f(10.0f + 3.0f * i, 240.0f);
    frame.keypoints.depth[i] = 0.5f + 0.05f * static_cast<float>(i);  // 0.5 m .. 10.45 m; 46 nearer than 2.8 m
  }
  frame.Prepare(640, 480);
  {
    Map map;
    LocalMappingState state;
    TrackedFrame f = frame;
    const KeyFrameHandle kf = InsertKeyFrame(map, state, context, f);
    EXPECT_EQ(map.points().size(), 101u);  // the 46 close ones are fewer than 100: the 101 nearest
    EXPECT_EQ(state.recent_points.size(), 101u);
    for (size_t i = 0; i < 200; ++i) EXPECT_EQ(f.points[i].is_null(), i >= 101) << i;
    // Each point sits at its keypoint's depth along its ray.
    const MapPoint& p = map.point(f.points[0]);
    EXPECT_NEAR(p.position.z(), 0.5, 1e-6);
    EXPECT_EQ(map.keyframe(kf).points[0], f.points[0]);
  }
  {
    Map map;
    LocalMappingState state;
    TrackedFrame f = frame;
    InsertKeyFrame(map, state, context, f, /*all_depth_points=*/true);
    EXPECT_EQ(map.points().size(), 200u);
  }
}

// A frame's close depth: the rig's (35 baselines) where at least 100 keypoints lie nearer, else
// as far as its 100 nearest, which the keyframe rule then counts as close.
TEST(LocalMapping, AFramesCloseDepthReachesItsHundredNearestKeypoints) {
  const SystemContext context = MakeContext(Sensor::kRgbd);
  std::vector<float> depth(200);
  for (size_t i = 0; i < 200; ++i) depth[i] = 0.5f + 0.05f * static_cast<float>(199 - i);  // 46 under 2.8 m
  depth[7] = -1;                                                                             // not measured
  // The nearest 100 measured lie at 0.5-5.45 m; the 101st, at 5.5 m, bounds them.
  EXPECT_NEAR(context.CloseDepth(depth), 5.5, 1e-6);
  for (float& d : depth) d *= 0.25f;  // 184 under 2.8 m
  EXPECT_DOUBLE_EQ(context.CloseDepth(depth), context.CloseDepth());
  std::vector<float> few(depth.begin(), depth.begin() + 100);  // 100 measured or fewer: the rig's
  for (float& d : few) d = 9.0f;
  EXPECT_DOUBLE_EQ(context.CloseDepth(few), context.CloseDepth());
  EXPECT_EQ(MakeContext(Sensor::kMonocular).CloseDepth(depth), 0.0);
}

// Two monocular keyframes 1 m apart seeing 40 points 10 m away (rays 5.7 degrees apart), 120 at
// 38 m (1.5 degrees: under the 2-degree floor, over the thin keyframe's 0.458) and 20 at 150 m
// (0.38 degrees). Keypoints are the exact projections with a descriptor of their own.
struct TwoMonocularKeyFrames {
  Map map;
  LocalMappingState state;
  std::vector<double> depth_of;  // per keypoint of the new keyframe
};

TwoMonocularKeyFrames MakeTwoMonocularKeyFrames(const SystemContext& context, size_t already_tracked) {
  TwoMonocularKeyFrames out;
  const PinholeCamera& camera = context.geometry.camera;
  std::vector<double> depths;
  for (int i = 0; i < 40; ++i) depths.push_back(10);
  for (int i = 0; i < 120; ++i) depths.push_back(38);
  for (int i = 0; i < 20; ++i) depths.push_back(150);
  const size_t n = depths.size() + already_tracked;
  KeyFrame a, b;
  a.resize(n);
  b.resize(n);
  b.T_cam_world.translation() = Eigen::Vector3d(-1, 0, 0);  // camera centre at x = +1 m
  for (size_t i = 0; i < n; ++i) {
    // A keypoint every 25 px from (40, 40) in the first keyframe; the tracked extras (already
    // carrying a point) lie at 10 m too.
    const double u = 40 + 25.0 * static_cast<double>(i % 22), v = 40 + 25.0 * static_cast<double>(i / 22);
    const double z = i < depths.size() ? depths[i] : 10.0;
    const Eigen::Vector3d X((u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z);
    const Eigen::Vector3d Xb = b.T_cam_world * X;
    a.uv.mutable_data()[i] = Eigen::Vector2f(static_cast<float>(u), static_cast<float>(v));
    b.uv.mutable_data()[i] = Eigen::Vector2f(static_cast<float>(camera.fx * Xb.x() / Xb.z() + camera.cx),
                                             static_cast<float>(camera.fy * Xb.y() / Xb.z() + camera.cy));
    uint64_t h = 0x9e3779b97f4a7c15ull * (i + 1);
    Descriptor d{};
    for (uint64_t& word : d) {
      h ^= h >> 31;
      h *= 0xbf58476d1ce4e5b9ull;
      word = h;
    }
    a.descriptor.mutable_data()[i] = d;
    b.descriptor.mutable_data()[i] = d;
    out.depth_of.push_back(z);
  }
  const KeyFrameHandle kb = out.map.AddKeyFrame(std::move(b));
  const KeyFrameHandle ka = out.map.AddKeyFrame(std::move(a));
  for (size_t i = depths.size(); i < n; ++i) {
    const PointHandle p = out.map.AddPoint(Eigen::Vector3d::Zero(), ka);
    out.map.AddObservation(p, ka, static_cast<uint32_t>(i));
    out.map.AddObservation(p, kb, static_cast<uint32_t>(i));
  }
  out.state.neighbours = {kb};
  out.state.snapshot = {out.map.keyframe(ka), out.map.keyframe(kb)};
  return out;
}

// Monocular new points need 2 degrees between their rays; a keyframe that would hold fewer points
// than thin_keyframe_points (twice the fading count, 200) also takes those down to the angle of 4
// pixels (4 / 500 rad, 0.458 degrees), widest first, up to that count, in the cells of an 8 x 8
// grid (80 x 60 px) where it holds no point: 84 of the 120 1.5-degree ones (36 share a cell with
// the 40 wide ones, the tracked ones lie below them), never the 0.38-degree ones.
TEST(LocalMapping, AThinMonocularKeyFrameTakesNarrowerRaysWhereItHoldsNoPoint) {
  const SystemContext context = MakeContext(Sensor::kMonocular);
  ASSERT_EQ(context.options.min_parallax_deg, 2.0);
  ASSERT_NEAR(context.options.thin_keyframe_parallax_deg, 4.0 / 500 * 180 / M_PI, 1e-12);
  ASSERT_EQ(context.options.keyframe_fading_inliers, 100);
  ASSERT_EQ(context.options.thin_keyframe_points, 200);
  auto count_at = [](const TwoMonocularKeyFrames& k, const std::vector<NewPoint>& found, double depth) {
    return std::count_if(found.begin(), found.end(), [&](const NewPoint& c) { return k.depth_of[c.i1] == depth; });
  };
  // Tracked points, and the narrow ones then taken: the 40 wide ones always.
  for (const auto& [tracked, narrow] : {std::pair{0, 84}, std::pair{50, 84}, std::pair{100, 60}, std::pair{160, 0}}) {
    SCOPED_TRACE(tracked);
    const TwoMonocularKeyFrames k = MakeTwoMonocularKeyFrames(context, tracked);
    const std::vector<NewPoint> found = FindNewPoints(k.state, context, {1.0, 400.0});
    EXPECT_EQ(count_at(k, found, 10), 40);
    EXPECT_EQ(count_at(k, found, 38), narrow);
    EXPECT_EQ(count_at(k, found, 150), 0);
    for (const NewPoint& c : found) EXPECT_NEAR(c.X_world.z(), k.depth_of[c.i1], 1e-3 * k.depth_of[c.i1]);
  }
  {
    // A floor under the 0.38-degree rays takes them too (their cells hold no point).
    SystemContext low = context;
    low.options.thin_keyframe_parallax_deg = 0.2;
    const TwoMonocularKeyFrames k = MakeTwoMonocularKeyFrames(low, 0);
    const std::vector<NewPoint> found = FindNewPoints(k.state, low, {1.0, 400.0});
    EXPECT_EQ(count_at(k, found, 38), 84);
    EXPECT_EQ(count_at(k, found, 150), 20);
  }
  {
    // Switched off (the thin floor at the floor): the wide ones alone.
    SystemContext off = context;
    off.options.thin_keyframe_parallax_deg = off.options.min_parallax_deg;
    const TwoMonocularKeyFrames k = MakeTwoMonocularKeyFrames(off, 0);
    const std::vector<NewPoint> found = FindNewPoints(k.state, off, {1.0, 400.0});
    EXPECT_EQ(count_at(k, found, 10), 40);
    EXPECT_EQ(count_at(k, found, 38), 0);
  }
}

TEST(LocalMapping, CullsKeyFramesWhosePointsOthersSeeAndKeepsTheProtectedOnes) {
  const SystemContext context = MakeContext(Sensor::kMonocular);
  Map map;
  constexpr size_t kPoints = 40, kKeyFrames = 5;
  std::vector<KeyFrameHandle> kfs;
  for (size_t k = 0; k < kKeyFrames; ++k) {
    KeyFrame kf = GridKeyFrame(kPoints);
    kf.T_cam_world.translation() = Eigen::Vector3d(0.1 * k, 0, 0);
    kfs.push_back(map.AddKeyFrame(std::move(kf)));
  }
  for (size_t i = 0; i < kPoints; ++i) {
    const PointHandle p = map.AddPoint(Eigen::Vector3d(0.01 * i, 0, 3), kfs[0]);
    for (KeyFrameHandle kf : kfs) map.AddObservation(p, kf, static_cast<uint32_t>(i));
  }
  for (KeyFrameHandle kf : kfs) map.UpdateCovisibility(kf);

  // Every point has 5 observers: keyframes 2, 3, 4 are redundant in turn until the points are
  // down to 3 observers. Keyframe 1 is protected (tracking's reference).
  LocalMappingState state;
  std::vector<KeyFrameHandle> erased;
  const KeyFrameHandle keep[] = {kfs[1]};
  CullKeyFrames(map, state, context, kfs[0], keep, [&](KeyFrameHandle h, const KeyFrame&) { erased.push_back(h); });
  EXPECT_EQ(erased.size(), 2u);
  EXPECT_TRUE(map.keyframes().contains(kfs[0]));
  EXPECT_TRUE(map.keyframes().contains(kfs[1]));
  for (KeyFrameHandle h : erased) {
    EXPECT_FALSE(map.keyframes().contains(h));
    EXPECT_NE(h, kfs[1]);
  }
  EXPECT_EQ(map.keyframes().size(), kKeyFrames - 2);
  // What is left keeps every point with at least 3 observers.
  for (PointHandle p : map.points().handles()) EXPECT_GE(map.point(p).observations.size(), 3u);
}

TEST(LocalMapping, FramesOfACulledKeyFrameFollowItsParent) {
  Map map;
  KeyFrame parent_kf = GridKeyFrame(1), child_kf = GridKeyFrame(1);
  parent_kf.T_cam_world.translation() = Eigen::Vector3d(1, 0, 0);
  const KeyFrameHandle parent = map.AddKeyFrame(std::move(parent_kf));
  const KeyFrameHandle child = map.AddKeyFrame(std::move(child_kf));
  CulledKeyFrames culled;
  culled[child] = {parent, Eigen::Isometry3d(Eigen::Translation3d(0, 2, 0))};
  map.EraseKeyFrame(child);
  AnchoredFramePose frame;
  frame.reference = child;
  frame.T_cam_ref = CompactPose(Eigen::Isometry3d(Eigen::Translation3d(0, 0, 3)));
  const Eigen::Isometry3d T = ResolveFramePose(map, culled, frame);
  EXPECT_TRUE(T.translation().isApprox(Eigen::Vector3d(1, 2, 3)));
}

}  // namespace
}  // namespace flatslam
