#include "mapping/camera_check.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

// The camera a map is given: KITTI-like, 1226x370, fx = fy = 707.
CameraGeometry Given(double fx) {
  Calibration calibration;
  calibration.sensor = Sensor::kMonocular;
  calibration.camera = {fx, fx, 613, 185, 1226, 370};
  return CameraGeometry::FromCalibration(calibration, 0, ScalePyramid::Make(8, 1.2f));
}

// Twelve keyframes 0.5 m apart along the camera's axis, turning `turn_deg` in all about the
// vertical; 600 points 5-40 m ahead, each kept where a keyframe sees it. Keypoints are where a
// camera of focal length true_fx and radial term true_k1 shows the points (x_d = x (1 + k1 r^2)),
// plus 0.5 px of noise; the map holds the true poses and points.
Map MapSeenBy(double true_fx, double true_k1, double turn_deg, size_t points = 600) {
  const CameraGeometry truth = Given(true_fx);
  const PinholeCamera& cam = truth.camera;
  std::mt19937 rng(3);
  std::normal_distribution<double> noise(0.0, 0.5);
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  Map map;
  std::vector<KeyFrameHandle> kfs;
  std::vector<Eigen::Isometry3d> poses;
  constexpr int kKeyFrames = 12;
  Eigen::Isometry3d T_world_cam = Eigen::Isometry3d::Identity();
  for (int k = 0; k < kKeyFrames; ++k) {
    poses.push_back(T_world_cam.inverse());
    T_world_cam = T_world_cam * Eigen::Translation3d(0, 0, 0.5) *
                  Eigen::AngleAxisd(turn_deg / (kKeyFrames - 1) * M_PI / 180, Eigen::Vector3d::UnitY());
  }
  // Points in front of the middle keyframe, spread over its view.
  const Eigen::Isometry3d middle = poses[kKeyFrames / 2].inverse();
  std::vector<Eigen::Vector3d> world;
  for (size_t i = 0; i < points; ++i) {
    const double z = 5 + 35 * uniform(rng);
    world.push_back(middle * Eigen::Vector3d((uniform(rng) - 0.5) * 1.6 * z, (uniform(rng) - 0.5) * 0.5 * z, z));
  }
  std::vector<std::vector<std::pair<size_t, uint32_t>>> seen(points);  // point -> (keyframe, keypoint)
  for (int k = 0; k < kKeyFrames; ++k) {
    KeyFrame kf;
    kf.id = static_cast<uint64_t>(k);
    kf.t_ns = k;
    kf.T_cam_world = poses[static_cast<size_t>(k)];
    std::vector<Eigen::Vector2f> uv;
    for (size_t i = 0; i < points; ++i) {
      const Eigen::Vector3d X = kf.T_cam_world * world[i];
      if (X.z() < 1) continue;
      const double x = X.x() / X.z(), y = X.y() / X.z(), d = 1 + true_k1 * (x * x + y * y);
      const double u = cam.cx + cam.fx * x * d + noise(rng), v = cam.cy + cam.fy * y * d + noise(rng);
      if (!truth.InImage(u, v)) continue;
      seen[i].emplace_back(static_cast<size_t>(k), static_cast<uint32_t>(uv.size()));
      uv.emplace_back(static_cast<float>(u), static_cast<float>(v));
    }
    kf.resize(uv.size());
    for (size_t j = 0; j < uv.size(); ++j) kf.uv.mutable_data()[j] = uv[j];
    kfs.push_back(map.AddKeyFrame(std::move(kf)));
  }
  for (size_t i = 0; i < points; ++i) {
    if (seen[i].size() < 2) continue;
    const PointHandle p = map.AddPoint(world[i], kfs[seen[i][0].first]);
    for (const auto& [k, keypoint] : seen[i]) map.AddObservation(p, kfs[k], keypoint);
  }
  return map;
}

TEST(CameraCheck, AgreesWithTheCameraThatMadeTheKeypoints) {
  const CameraGeometry g = Given(707);
  const CameraCheck check = CheckCameraModel(MapSeenBy(707, 0, 40), g);
  ASSERT_TRUE(check.ok);
  EXPECT_GT(check.observations, 3000u);
  EXPECT_NEAR(check.focal_scale, 1.0, 4 * check.focal_scale_sigma);
  EXPECT_NEAR(check.k1, 0.0, 4 * check.k1_sigma);
  EXPECT_LT(check.focal_scale_sigma, 0.005);
  EXPECT_LT(check.k1_sigma, 0.003);
  EXPECT_NEAR(check.rmse_after_px, 0.5, 0.1);  // the keypoints' own noise
  EXPECT_NE(DescribeCameraCheck(check, g.camera).find("agree with the camera model"), std::string::npos);
}

// Images with radial distortion the calibration leaves out, and a focal length 2% off.
TEST(CameraCheck, FindsARadialTermAndAFocalLengthTheCalibrationMisses) {
  {
    const CameraGeometry g = Given(707);
    const CameraCheck check = CheckCameraModel(MapSeenBy(707, 0.02, 40), g);
    ASSERT_TRUE(check.ok);
    EXPECT_NEAR(check.k1, 0.02, 0.003);
    EXPECT_GT(std::abs(check.k1) / check.k1_sigma, 5.0);
    EXPECT_GT(check.rmse_before_px, 1.5 * check.rmse_after_px);
    EXPECT_NE(DescribeCameraCheck(check, g.camera).find("disagree"), std::string::npos);
  }
  {
    const CameraGeometry g = Given(707 * 1.02);
    const CameraCheck check = CheckCameraModel(MapSeenBy(707, 0, 40), g);
    ASSERT_TRUE(check.ok);
    EXPECT_NEAR(check.focal_scale * 707 * 1.02, 707, 707 * 0.004);
    EXPECT_NE(DescribeCameraCheck(check, g.camera).find("disagree"), std::string::npos);
  }
}

// Along a straight path a focal length is a lateral stretch of the scene: the same keypoints,
// so the check must say it cannot tell rather than name a value.
TEST(CameraCheck, AStraightPathLeavesTheFocalLengthOpen) {
  const CameraGeometry g = Given(707);
  const CameraCheck turning = CheckCameraModel(MapSeenBy(707, 0, 40), g);
  const CameraCheck straight = CheckCameraModel(MapSeenBy(707, 0, 0), g);
  ASSERT_TRUE(turning.ok);
  ASSERT_TRUE(straight.ok);
  EXPECT_GT(straight.focal_scale_sigma, 3 * turning.focal_scale_sigma);
  EXPECT_LT(std::abs(straight.focal_scale - 1) / straight.focal_scale_sigma, 4.0);
}

// A share of the points (CameraCheckOptions::max_points) finds the same lens, its standard error
// larger by about the root of the share; the corner shift says what the lens does to the image.
TEST(CameraCheck, AShareOfThePointsFindsTheSameLens) {
  const CameraGeometry g = Given(707);
  const Map map = MapSeenBy(707, 0.02, 40);
  const CameraCheck all = CheckCameraModel(map, g);
  CameraCheckOptions options;
  options.max_points = all.points / 3;
  const CameraCheck share = CheckCameraModel(map, g, options);
  ASSERT_TRUE(all.ok);
  ASSERT_TRUE(share.ok);
  EXPECT_LE(share.points, options.max_points);
  EXPECT_GE(share.points, options.max_points / 2);
  EXPECT_NEAR(share.k1, 0.02, 0.003);
  EXPECT_GT(share.k1_sigma, 1.3 * all.k1_sigma);
  EXPECT_LT(share.k1_sigma, 2.5 * all.k1_sigma);
  EXPECT_TRUE(CameraCheckDisagrees(share));
  // k1 = 0.02 at the corner of a 1226x370 image at fx 707 (r^2 about 0.82): about 10.5 px.
  CameraCheck lens;
  lens.ok = true;
  lens.k1 = 0.02;
  const double x = 613.0 / 707, y = 185.0 / 707;
  EXPECT_NEAR(CameraCheckCornerShiftPx(lens, g.camera), 707 * 0.02 * (x * x + y * y) * std::hypot(x, y), 1e-9);
  EXPECT_NEAR(CameraCheckCornerShiftPx(CameraCheck{}, g.camera), 0, 1e-12);
}

TEST(CameraCheck, NeedsEnoughObservations) {
  EXPECT_FALSE(CheckCameraModel(MapSeenBy(707, 0, 40, 20), Given(707)).ok);
  EXPECT_FALSE(CheckCameraModel(Map(), Given(707)).ok);
}

}  // namespace
}  // namespace flatslam
