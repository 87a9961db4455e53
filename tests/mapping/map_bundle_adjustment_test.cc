#include "mapping/map_bundle_adjustment.h"

#include <cmath>
#include <limits>

#include <gtest/gtest.h>

#include "geometry/geometry_fixtures.h"

namespace flatslam {
namespace {

constexpr double kBaseline = 0.5;

CameraGeometry Geometry() {
  CameraGeometry g;
  g.camera = testing::TestCamera();
  g.bf = kBaseline * g.camera.fx;
  g.pyramid = ScalePyramid::Make(8, 1.2f);
  return g;
}

// Keyframes along x at 1 m spacing, looking down +z; points 0-3 at depths 10, 13, 16, 19 m, the
// others at 6 m. Keypoint j of a keyframe is point j projected exactly, with stereo and octave j % 3.
struct Scene {
  Map map;
  std::vector<KeyFrameHandle> kfs;
  std::vector<PointHandle> pts;

  Scene(size_t keyframes, size_t points) {
    const CameraGeometry g = Geometry();
    for (size_t i = 0; i < keyframes; ++i) {
      KeyFrame kf;
      kf.resize(points);
      kf.T_cam_world.translation() = Eigen::Vector3d(-static_cast<double>(i), 0, 0);
      for (size_t j = 0; j < points; ++j) {
        const Eigen::Vector3d X = kf.T_cam_world * Position(j);
        kf.uv.mutable_data()[j] = Eigen::Vector2f(static_cast<float>(g.camera.fx * X.x() / X.z() + g.camera.cx),
                                                  static_cast<float>(g.camera.fy * X.y() / X.z() + g.camera.cy));
        kf.depth.mutable_data()[j] = static_cast<float>(X.z());
        kf.right_u.mutable_data()[j] = static_cast<float>(kf.uv[j].x() - g.bf / X.z());
        kf.octave.mutable_data()[j] = static_cast<uint8_t>(j % 3);
      }
      kfs.push_back(map.AddKeyFrame(std::move(kf)));
    }
    for (size_t j = 0; j < points; ++j) pts.push_back(map.AddPoint(Position(j), kfs[0]));
  }
  static Eigen::Vector3d Position(size_t j) {
    return {static_cast<double>(j) - 2, 0, j < 4 ? 10.0 + 3.0 * static_cast<double>(j) : 6.0};
  }
  void See(size_t kf, size_t point) { map.AddObservation(pts[point], kfs[kf], static_cast<uint32_t>(point)); }
};

TEST(StereoDepthRule, CutsStereoBeyondTheFixedDepthOrTheMedian) {
  EXPECT_TRUE(std::isinf(StereoDepthRule::ForRig(false, 0.5, 35).fixed_far_m));  // RGB-D, monocular
  EXPECT_TRUE(std::isinf(StereoDepthRule::ForRig(true, 0.5, 0).fixed_far_m));    // cut switched off
  const StereoDepthRule rule = StereoDepthRule::ForRig(true, 0.5, 35);
  EXPECT_DOUBLE_EQ(rule.fixed_far_m, 17.5);
  const std::vector<float> near = {2, 3, -1, 4, 5, 0};  // median of the measured: 4
  EXPECT_DOUBLE_EQ(rule.FarDepth(near), 17.5);
  const std::vector<float> far = {30, 40, 50, -1, 60, 70};  // most texture far: the median wins
  EXPECT_DOUBLE_EQ(rule.FarDepth(far), 50);
  EXPECT_DOUBLE_EQ(rule.FarDepth({}), 17.5);
  EXPECT_EQ(rule.RightU(300.f, 100.f, 20.f, 17.5, 1.0), -1);
  EXPECT_EQ(rule.RightU(300.f, 100.f, 10.f, 17.5, 1.0), 100);
  EXPECT_EQ(rule.RightU(300.f, -1.f, 10.f, 17.5, 1.0), -1);  // no match
}

// Under one pixel of its level, a matched disparity is pulled towards zero by the sub-pixel step:
// such an observation is monocular on a stereo rig, whatever its depth; RGB-D depth is no match.
TEST(StereoDepthRule, CutsStereoUnderAPixelOfTheKeypointsLevel) {
  const StereoDepthRule rule = StereoDepthRule::ForRig(true, 0.11, 35);
  EXPECT_DOUBLE_EQ(rule.min_level_px, kFarStereoLevelPixels);
  const double far = rule.FarDepth(std::vector<float>{90, 100, 110});  // the median, 100 m
  EXPECT_EQ(rule.RightU(300.f, 299.2f, 60.f, far, 1.0), -1);       // 0.8 px on level 0
  EXPECT_EQ(rule.RightU(300.f, 298.8f, 40.f, far, 1.0), 298.8f);   // 1.2 px on level 0
  EXPECT_EQ(rule.RightU(300.f, 298.8f, 40.f, far, 1.44), -1);      // 1.2 px on level 2 (1.2^2)
  EXPECT_EQ(rule.RightU(300.f, 298.2f, 27.f, far, 1.44), 298.2f);  // 1.8 px on level 2
  const StereoDepthRule off = StereoDepthRule::ForRig(true, 0.11, 35, 0);
  EXPECT_EQ(off.RightU(300.f, 299.9f, 500.f, 1000, 1.44), 299.9f);
  const StereoDepthRule rgbd = StereoDepthRule::ForRig(false, 0.08, 35);
  EXPECT_EQ(rgbd.min_level_px, 0);
  EXPECT_EQ(rgbd.RightU(300.f, 299.9f, 300.f, rgbd.FarDepth(std::vector<float>{1, 2}), 1.44), 299.9f);
}

TEST(MapBundleAdjustment, FreeKeyframesTheirPointsAndEveryOtherObserverFixed) {
  Scene s(4, 6);
  // kf0 and kf1 are free; kf2 sees point 1 (enters fixed); kf3 sees only point 5, which no free
  // keyframe sees (stays out); point 4 has one observer (out with min_observations 2).
  for (size_t j : {0, 1, 2, 3}) s.See(0, j);
  for (size_t j : {0, 1, 2, 3, 4}) s.See(1, j);
  s.See(2, 1);
  s.See(2, 5);
  s.See(3, 5);
  const CameraGeometry g = Geometry();
  // A fixed cut at 12 m, nearer than the keyframes' median measured depth (13 m): that is the cut,
  // so points 2 and 3 (16 and 19 m) enter as monocular observations.
  const StereoDepthRule stereo{12.0};
  MapBundleAdjustment ba;
  const std::vector<KeyFrameHandle> free = {s.kfs[1], s.kfs[0], s.kfs[1], KeyFrameHandle::null()};
  BuildMapBundleAdjustment(s.map, g, stereo, free, s.kfs[0], 2, &ba);
  ASSERT_EQ(ba.keyframes.size(), 3u);
  EXPECT_EQ(ba.keyframes[0], s.kfs[1]);  // the order of `free`, duplicates and dead handles dropped
  EXPECT_EQ(ba.keyframes[1], s.kfs[0]);
  EXPECT_EQ(ba.keyframes[2], s.kfs[2]);  // observer outside the window
  EXPECT_FALSE(ba.problem.poses[0].fixed);
  EXPECT_TRUE(ba.problem.poses[1].fixed);  // the anchor
  EXPECT_TRUE(ba.problem.poses[2].fixed);
  EXPECT_EQ(ba.points, (std::vector<PointHandle>{s.pts[0], s.pts[1], s.pts[2], s.pts[3]}));
  ASSERT_EQ(ba.problem.points.size(), 4u);
  EXPECT_EQ(ba.problem.points[2], Scene::Position(2));
  EXPECT_EQ(ba.problem.observations.size(), 9u);  // 4 + 4 + point 1 from kf2
  EXPECT_DOUBLE_EQ(ba.problem.baseline_m, kBaseline);
  int monocular = 0;
  for (const BundleAdjustmentObservation& o : ba.problem.observations) {
    monocular += o.right_u < 0;
    const KeyFrame& kf = s.map.keyframe(ba.keyframes[o.pose_index]);
    const uint32_t keypoint = static_cast<uint32_t>(o.point_index);  // point j is keypoint j here
    EXPECT_EQ(o.uv, kf.uv[keypoint].cast<double>());
    EXPECT_FLOAT_EQ(o.inv_sigma2, g.pyramid.inv_sigma2[kf.octave[keypoint]]);
    ASSERT_DOUBLE_EQ(stereo.FarDepth(kf.depth), 13.0);
    if (kf.depth[keypoint] > 13.0)
      EXPECT_EQ(o.right_u, -1) << "beyond the cut: monocular";
    else
      EXPECT_EQ(o.right_u, kf.right_u[keypoint]);
  }
  EXPECT_EQ(monocular, 4);  // points 2 and 3, each seen by kf0 and kf1

  // A monocular camera never makes stereo observations, whatever the keyframes hold.
  CameraGeometry mono = g;
  mono.bf = 0;
  BuildMapBundleAdjustment(s.map, mono, StereoDepthRule{}, free, s.kfs[0], 1, &ba);
  EXPECT_EQ(ba.points.size(), 5u);  // point 4 now enters
  for (const BundleAdjustmentObservation& o : ba.problem.observations) EXPECT_EQ(o.right_u, -1);
}

TEST(MapBundleAdjustment, ApplyWritesFreePosesAndPointsAndErasesOutliers) {
  Scene s(3, 4);
  for (size_t i = 0; i < 3; ++i)
    for (size_t j = 0; j < 4; ++j) s.See(i, j);
  MapBundleAdjustment ba;
  const std::vector<KeyFrameHandle> free = {s.kfs[0], s.kfs[1]};
  BuildMapBundleAdjustment(s.map, Geometry(), StereoDepthRule{}, free, s.kfs[0], 1, &ba);
  ASSERT_EQ(ba.keyframes.size(), 3u);  // kf2 sees every point: fixed
  // A "solution": every pose and point moved by 1 m in y.
  for (BundleAdjustmentPose& pose : ba.problem.poses) pose.T_cam_world.translation().y() += 1;
  for (Eigen::Vector3d& X : ba.problem.points) X.y() += 1;
  BundleAdjustmentResult result;
  result.success = true;
  result.outlier.assign(ba.problem.observations.size(), false);
  size_t flagged = 0;
  for (size_t k = 0; k < ba.problem.observations.size(); ++k) {
    const BundleAdjustmentObservation& o = ba.problem.observations[k];
    if (ba.keyframes[o.pose_index] == s.kfs[1] && ba.points[o.point_index] == s.pts[2]) {
      result.outlier[k] = true;
      ++flagged;
    }
  }
  ASSERT_EQ(flagged, 1u);
  s.map.ErasePoint(s.pts[3]);  // died while the problem was solved

  EXPECT_EQ(ApplyMapBundleAdjustment(ba, result, /*erase_outliers=*/true, &s.map), 1u);
  EXPECT_EQ(s.map.keyframe(s.kfs[0]).T_cam_world.translation().y(), 0);  // anchor: fixed
  EXPECT_EQ(s.map.keyframe(s.kfs[1]).T_cam_world.translation().y(), 1);
  EXPECT_EQ(s.map.keyframe(s.kfs[2]).T_cam_world.translation().y(), 0);  // outside the window
  EXPECT_EQ(s.map.point(s.pts[0]).position.y(), 1);
  EXPECT_FALSE(s.map.points().contains(s.pts[3]));
  EXPECT_TRUE(s.map.keyframe(s.kfs[1]).points[2].is_null());  // the outlier observation is gone
  EXPECT_EQ(s.map.point(s.pts[2]).observations.size(), 2u);
  EXPECT_EQ(s.map.Validate(), "");

  // Without erase_outliers the observations stay.
  BuildMapBundleAdjustment(s.map, Geometry(), StereoDepthRule{}, free, s.kfs[0], 1, &ba);
  result.outlier.assign(ba.problem.observations.size(), true);
  EXPECT_EQ(ApplyMapBundleAdjustment(ba, result, /*erase_outliers=*/false, &s.map), 0u);
  EXPECT_EQ(s.map.point(s.pts[0]).observations.size(), 3u);
}

}  // namespace
}  // namespace flatslam
