#include "mapping/rig_check.h"

#include <cmath>
#include <random>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

CameraGeometry Rig() {
  Calibration calibration;
  calibration.sensor = Sensor::kStereo;
  calibration.camera = {500, 500, 320, 240, 640, 480};
  calibration.baseline_m = 0.5;
  return CameraGeometry::FromCalibration(calibration, 0, ScalePyramid::Make(8, 1.2f));
}

// Eight keyframes 1 m apart sideways, points at 4-80 m seen by all of them, exact
// left pixels and right pixels that an offset rig shifts: every disparity `offset` pixels larger,
// plus Gaussian noise.
Map MapOfARig(const CameraGeometry& g, double offset, double noise, size_t points) {
  Map map;
  std::mt19937 rng(7);
  std::normal_distribution<double> gauss(0.0, noise);
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  std::vector<Eigen::Vector3d> world;
  for (size_t i = 0; i < points; ++i) {
    const double z = 4 + 76 * uniform(rng) * uniform(rng);
    world.emplace_back((uniform(rng) - 0.5) * 0.8 * z, (uniform(rng) - 0.5) * 0.6 * z, z);
  }
  std::vector<KeyFrameHandle> kfs;
  for (int k = 0; k < 8; ++k) {
    KeyFrame kf;
    kf.t_ns = k;
    kf.T_cam_world.translation() = Eigen::Vector3d(-1.0 * k, 0, 0);
    kf.resize(points);
    for (size_t i = 0; i < points; ++i) {
      const Eigen::Vector3d x = kf.T_cam_world * world[i];
      const double u = g.camera.fx * x.x() / x.z() + g.camera.cx, v = g.camera.fy * x.y() / x.z() + g.camera.cy;
      kf.uv.mutable_data()[i] = Eigen::Vector2f(u + gauss(rng), v + gauss(rng));
      kf.right_u.mutable_data()[i] = static_cast<float>(u - g.bf / x.z() - offset + gauss(rng));
      kf.depth.mutable_data()[i] = static_cast<float>(x.z());
    }
    kfs.push_back(map.AddKeyFrame(std::move(kf)));
  }
  for (size_t i = 0; i < points; ++i) {
    const PointHandle p = map.AddPoint(world[i], kfs[0]);
    for (KeyFrameHandle kf : kfs) map.AddObservation(p, kf, static_cast<uint32_t>(i));
  }
  return map;
}

TEST(RigCheck, FindsTheOffsetARigAddsToEveryDisparity) {
  const CameraGeometry g = Rig();
  for (const double offset : {0.0, -0.1, 0.25}) {
    const Map map = MapOfARig(g, offset, 0.1, 400);
    const DisparityOffsetFit fit = FitDisparityOffset(map, g);
    ASSERT_TRUE(fit.ok);
    EXPECT_NEAR(fit.offset_px, offset, 0.02) << "offset " << offset;
    EXPECT_LT(fit.offset_sigma_px, 0.01);
    EXPECT_GT(fit.observations, 2000u);
    EXPECT_EQ(fit.points, 400u);
  }
}

TEST(RigCheck, NeedsAStereoRigAndEnoughPoints) {
  const CameraGeometry g = Rig();
  EXPECT_FALSE(FitDisparityOffset(MapOfARig(g, 0.1, 0.1, 10), g).ok) << "80 observations are too few";
  CameraGeometry mono = g;
  mono.bf = 0;
  EXPECT_FALSE(FitDisparityOffset(MapOfARig(g, 0.1, 0.1, 400), mono).ok);
  EXPECT_FALSE(FitDisparityOffset(Map(), g).ok);
}

}  // namespace
}  // namespace flatslam
