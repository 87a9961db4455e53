#include "io/synthetic.h"

#include <cmath>
#include <cstdio>
#include <thread>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>

#include "core/error.h"

namespace flatslam {
namespace {

SyntheticOptions SmallOptions(Sensor sensor) {
  SyntheticOptions o;
  o.width = 320;
  o.height = 240;
  o.duration_s = 40;
  o.sensor = sensor;
  return o;
}

// Bilinear intensity at a sub-pixel position (x, y) of a CV_8UC1 image.
double Bilinear(const cv::Mat& img, double x, double y) {
  const int x0 = static_cast<int>(std::floor(x)), y0 = static_cast<int>(std::floor(y));
  const double fx = x - x0, fy = y - y0;
  auto at = [&](int r, int c) { return static_cast<double>(img.at<uint8_t>(r, c)); };
  return (1 - fy) * ((1 - fx) * at(y0, x0) + fx * at(y0, x0 + 1)) +
         fy * ((1 - fx) * at(y0 + 1, x0) + fx * at(y0 + 1, x0 + 1));
}

// Median |I_a(p) - I_b(project(p))| over pixels of view a whose depth is known, warping
// with the exact poses: small only if images, depth and poses agree.
double MedianWarpError(const SyntheticScene& scene, const Eigen::Isometry3d& T_world_a, const cv::Mat& a,
                       const cv::Mat& depth_a, const Eigen::Isometry3d& T_world_b, const cv::Mat& b) {
  const PinholeCamera& cam = scene.calibration().camera;
  const Eigen::Isometry3d T_b_a = T_world_b.inverse() * T_world_a;
  std::vector<double> errors;
  for (int v = 4; v < a.rows - 4; v += 3) {
    for (int u = 4; u < a.cols - 4; u += 3) {
      const float z = depth_a.at<float>(v, u);
      if (z <= 0) continue;
      const Eigen::Vector3d Xa((u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z);
      const Eigen::Vector3d Xb = T_b_a * Xa;
      if (Xb.z() < 0.1) continue;
      const double ub = cam.fx * Xb.x() / Xb.z() + cam.cx, vb = cam.fy * Xb.y() / Xb.z() + cam.cy;
      if (ub < 1 || vb < 1 || ub > b.cols - 2 || vb > b.rows - 2) continue;
      errors.push_back(std::abs(a.at<uint8_t>(v, u) - Bilinear(b, ub, vb)));
    }
  }
  if (errors.size() < 1000) return 1e9;
  std::nth_element(errors.begin(), errors.begin() + errors.size() / 2, errors.end());
  return errors[errors.size() / 2];
}

TEST(SyntheticScene, RendersEveryBuiltInScene) {
  for (const std::string& name : SyntheticSceneNames()) {
    SyntheticScene scene(MakeScene(name), SmallOptions(Sensor::kMonocular));
    const Frame f = scene.Render(scene.frame_count() / 3);
    ASSERT_EQ(f.left.type(), CV_8UC1) << name;
    ASSERT_EQ(f.left.cols, 320);
    ASSERT_EQ(f.left.rows, 240);
    cv::Scalar mean, stddev;
    cv::meanStdDev(f.left, mean, stddev);
    EXPECT_GT(stddev[0], 25.0) << name << ": texture too flat for features";
  }
}

TEST(SyntheticScene, DeterministicAcrossThreadsAndSeeds) {
  SyntheticScene scene(MakeScene("room"), SmallOptions(Sensor::kStereo));
  const Frame a = scene.Render(17);
  Frame b;
  std::thread([&] { b = scene.Render(17); }).join();
  EXPECT_EQ(cv::norm(a.left, b.left, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(a.right, b.right, cv::NORM_INF), 0.0);
  SyntheticOptions other = SmallOptions(Sensor::kStereo);
  other.seed = 2;
  SyntheticScene scene2(MakeScene("room"), other);
  const Frame c = scene2.Render(17);
  EXPECT_GT(cv::norm(a.left, c.left, cv::NORM_L1), 0.0) << "noise must depend on the seed";
  // Same world, so the noise-free content agrees: the difference is only noise.
  cv::Mat diff;
  cv::absdiff(a.left, c.left, diff);
  EXPECT_LT(cv::mean(diff)[0], 4.0);
}

TEST(SyntheticScene, DepthAndPosesAreExactAcrossStereoAndTime) {
  SyntheticOptions o = SmallOptions(Sensor::kStereo);
  o.pixel_noise_sigma = 0;
  for (const char* name : {"room", "street"}) {
    SyntheticScene scene(MakeScene(name), o);
    const size_t i = 101;
    const Eigen::Isometry3d T_left = scene.PoseAt(scene.timestamp_ns(i) * 1e-9);
    const Eigen::Isometry3d T_right = T_left * Eigen::Translation3d(scene.calibration().baseline_m, 0, 0);
    cv::Mat left, depth, right, later;
    scene.RenderView(T_left, 0, &left, &depth);
    scene.RenderView(T_right, 0, &right, nullptr);
    const Frame f = scene.Render(i);
    EXPECT_EQ(cv::norm(f.left, left, cv::NORM_INF), 0.0);
    EXPECT_EQ(cv::norm(f.right, right, cv::NORM_INF), 0.0);
    const Eigen::Isometry3d T_later = scene.PoseAt(scene.timestamp_ns(i + 6) * 1e-9);
    scene.RenderView(T_later, 0, &later, nullptr);
    const double stereo_error = MedianWarpError(scene, T_left, left, depth, T_right, right);
    const double temporal_error = MedianWarpError(scene, T_left, left, depth, T_later, later);
    // A pose off by one degree (about 4 px here) must show up: the warp is then far worse.
    const Eigen::Isometry3d T_wrong = T_later * Eigen::AngleAxisd(M_PI / 180, Eigen::Vector3d::UnitY());
    const double wrong_error = MedianWarpError(scene, T_left, left, depth, T_wrong, later);
    std::printf("%s: median warp error stereo %.2f, 6 frames later %.2f, with 1 deg error %.2f\n",
                name, stereo_error, temporal_error, wrong_error);
    // Measured: below 1 grey level for both (noise-free images, bilinear warp).
    EXPECT_LT(stereo_error, 1.5) << name;
    EXPECT_LT(temporal_error, 2.0) << name;
    EXPECT_GT(wrong_error, 5 * temporal_error + 4) << name;
  }
}

TEST(SyntheticScene, DepthNoiseFollowsItsModel) {
  SyntheticOptions o = SmallOptions(Sensor::kRgbd);
  o.pixel_noise_sigma = 0;
  SyntheticScene scene(MakeScene("room"), o);
  const Frame f = scene.Render(50);
  cv::Mat gray, exact;
  scene.RenderView(scene.PoseAt(scene.timestamp_ns(50) * 1e-9), 0, &gray, &exact);
  double sum = 0, sum_sq = 0;
  int n = 0;
  for (int v = 0; v < exact.rows; ++v) {
    for (int u = 0; u < exact.cols; ++u) {
      const float z = exact.at<float>(v, u), d = f.depth.at<float>(v, u);
      if (z <= 0 || d <= 0) continue;
      const double normalized = (d - z) / (o.depth_noise_k * z * z);
      sum += normalized;
      sum_sq += normalized * normalized;
      ++n;
    }
  }
  ASSERT_GT(n, 50000);
  EXPECT_NEAR(sum / n, 0.0, 0.05);
  EXPECT_NEAR(std::sqrt(sum_sq / n), 1.0, 0.1);
}

TEST(SyntheticScene, TrajectoryLoopsAtConstantSpeed) {
  SyntheticScene scene(MakeScene("room"), SmallOptions(Sensor::kMonocular));
  const Trajectory gt = scene.GroundTruth();
  ASSERT_EQ(gt.size(), scene.frame_count());
  const double step = scene.description().agents[0].speed_mps / scene.options().frame_rate_hz;
  for (size_t i = 1; i < gt.size(); ++i) {
    ASSERT_GT(gt[i].t_ns, gt[i - 1].t_ns);
    const Eigen::Vector3d d = gt[i].T_world_cam.translation() - gt[i - 1].T_world_cam.translation();
    EXPECT_NEAR(d.head<2>().norm(), step, 0.2 * step) << "frame " << i;
    EXPECT_LT((gt[i].T_world_cam.linear().transpose() * gt[i].T_world_cam.linear() -
               Eigen::Matrix3d::Identity()).norm(), 1e-9);
  }
  // After one lap the camera is back near its start: a revisit.
  const double lap_s = scene.loop_length_m() / scene.description().agents[0].speed_mps;
  const size_t lap = static_cast<size_t>(lap_s * scene.options().frame_rate_hz);
  ASSERT_LT(lap, gt.size());
  EXPECT_LT((gt[lap].T_world_cam.translation() - gt[0].T_world_cam.translation()).head<2>().norm(), 0.1);
}

TEST(SyntheticScene, EveryPathIsSmooth) {
  // No kinks: the camera turns at most a few degrees between frames in every scene and agent.
  for (const std::string& name : SyntheticSceneNames()) {
    const SceneDescription description = MakeScene(name);
    for (int agent = 0; agent < static_cast<int>(description.agents.size()); ++agent) {
      SyntheticOptions o = SmallOptions(Sensor::kMonocular);
      o.agent = agent;
      o.duration_s = description.default_duration_s;
      const Trajectory gt = SyntheticScene(description, o).GroundTruth();
      double worst = 0;
      for (size_t i = 1; i < gt.size(); ++i) {
        const Eigen::AngleAxisd step(gt[i - 1].T_world_cam.linear().transpose() * gt[i].T_world_cam.linear());
        worst = std::max(worst, step.angle() * 180 / M_PI);
      }
      EXPECT_LT(worst, 4.0) << name << " agent " << agent;
    }
  }
}

TEST(SyntheticScene, TownAgentsOverlapOnlyInPart) {
  SyntheticOptions o = SmallOptions(Sensor::kMonocular);
  o.duration_s = 60;
  std::vector<Trajectory> paths;
  for (int agent = 0; agent < 3; ++agent) {
    o.agent = agent;
    paths.push_back(SyntheticScene(MakeScene("town"), o).GroundTruth());
  }
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      if (a == b) continue;
      size_t shared = 0;
      for (const TimedPose& p : paths[a]) {
        for (const TimedPose& q : paths[b]) {
          if ((p.T_world_cam.translation() - q.T_world_cam.translation()).norm() < 2.0) {
            ++shared;
            break;
          }
        }
      }
      const double fraction = static_cast<double>(shared) / paths[a].size();
      EXPECT_GT(fraction, 0.05) << "agents " << a << " and " << b << " never meet";
      EXPECT_LT(fraction, 0.8) << "agents " << a << " and " << b << " follow the same path";
    }
  }
}

TEST(SyntheticScene, RejectsBadSpecsAndOptions) {
  std::string scene;
  SyntheticOptions o;
  EXPECT_THROW(MakeScene("moon"), Error);
  EXPECT_THROW(ParseSyntheticSpec("room:width", &scene, &o), Error);
  EXPECT_THROW(ParseSyntheticSpec("room:colour=3", &scene, &o), Error);
  EXPECT_THROW(ParseSyntheticSpec("room:fps=fast", &scene, &o), Error);
  ParseSyntheticSpec("town:agent=2,duration=5,sensor=rgbd", &scene, &o);
  EXPECT_EQ(scene, "town");
  EXPECT_EQ(o.agent, 2);
  EXPECT_EQ(o.duration_s, 5);
  EXPECT_EQ(o.sensor, Sensor::kRgbd);
  o.agent = 3;
  EXPECT_THROW(SyntheticScene(MakeScene("town"), o), Error);
  SyntheticOptions bad;
  bad.width = 0;
  EXPECT_FALSE(bad.Check());
  EXPECT_THROW(SyntheticScene(MakeScene("room"), bad), Error);
}

}  // namespace
}  // namespace flatslam
