#include "io/synthetic.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <cstring>
#include <cstdio>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>

#include "core/cpu_features.h"
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
    std::printf("%s: median warp error stereo %.2f, 6 frames later %.2f, with 1 deg error %.2f\n", name, stereo_error,
                temporal_error, wrong_error);
    // Measured: below 1 grey level for both (noise-free images, bilinear warp).
    EXPECT_LT(stereo_error, 1.5) << name;
    EXPECT_LT(temporal_error, 2.0) << name;
    EXPECT_GT(wrong_error, 5 * temporal_error + 4) << name;
  }
}

// A coarse mip level must show the texture where the finest one does: a wall seen from eight
// times as far (mip level 2.7 of a 2x pyramid) is the near view (level 0) shrunk about the
// principal point. Sampling a level half a texel off its pyrDown grid moved the texture by up to
// half a pixel with the distance, so features expanded slower than the scene under forward motion
// (stereo trajectories on the town 0.4% short).
TEST(SyntheticScene, TextureSeenFromFarLandsWhereItDoesSeenFromNear) {
  SceneDescription scene;
  scene.name = "wall";
  scene.quads.push_back(MakeQuad({-3, -3, 0}, {6, 0, 0}, {0, 6, 0}, 96, 1.0f));
  CameraPath path;
  path.control_points = {{0, 0, -10}, {1, 0, -10}, {1, 1, -10}, {0, 1, -10}};
  scene.agents.push_back(path);
  SyntheticOptions o;
  o.width = 640;
  o.height = 480;
  o.fx = 480;  // footprints 96 * z / 480 texels: 0.8 at 4 m, 6.4 at 32 m
  o.pixel_noise_sigma = 0;
  const SyntheticScene wall(scene, o);
  constexpr double kNear = 4, kFar = 32, kZoom = kFar / kNear;
  cv::Mat near_view, far_view;
  wall.RenderView(Eigen::Isometry3d(Eigen::Translation3d(0, 0, -kNear)), 0, &near_view, nullptr);
  wall.RenderView(Eigen::Isometry3d(Eigen::Translation3d(0, 0, -kFar)), 0, &far_view, nullptr);
  // The near view low-passed to about the far view's footprint, then sampled at the far view's
  // pixels: far pixel u sees what near pixel cx + 8 (u - cx) sees.
  const PinholeCamera& cam = wall.calibration().camera;
  cv::Mat near_blurred, near_f, far_f;
  near_view.convertTo(near_f, CV_32F);
  far_view.convertTo(far_f, CV_32F);
  cv::GaussianBlur(near_f, near_blurred, cv::Size(0, 0), 0.5 * kZoom);
  constexpr int kSide = 64;  // centre crop of the far view: 4.3 m of the 6 m wall
  cv::Mat map_x(kSide, kSide, CV_32F), map_y(kSide, kSide, CV_32F);
  const int u0 = static_cast<int>(cam.cx) - kSide / 2, v0 = static_cast<int>(cam.cy) - kSide / 2;
  for (int r = 0; r < kSide; ++r) {
    for (int c = 0; c < kSide; ++c) {
      map_x.at<float>(r, c) = static_cast<float>(cam.cx + kZoom * (u0 + c - cam.cx));
      map_y.at<float>(r, c) = static_cast<float>(cam.cy + kZoom * (v0 + r - cam.cy));
    }
  }
  cv::Mat shrunk;
  cv::remap(near_blurred, shrunk, map_x, map_y, cv::INTER_LINEAR);
  cv::Mat far_crop = far_f(cv::Rect(u0, v0, kSide, kSide)).clone();
  cv::Mat window;
  cv::createHanningWindow(window, cv::Size(kSide, kSide), CV_32F);
  const cv::Point2d shift = cv::phaseCorrelate(shrunk, far_crop, window);
  std::printf("far view against the shrunk near view: %+.3f %+.3f px\n", shift.x, shift.y);
  // Measured: +0.025 / +0.021 px; +0.48 px in both directions with the off-grid sampling.
  EXPECT_LT(std::abs(shift.x), 0.1);
  EXPECT_LT(std::abs(shift.y), 0.1);
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

TEST(SyntheticScene, StructuredLightDepthIsQuantizedShadowedAndRanged) {
  SyntheticOptions o = SmallOptions(Sensor::kRgbd);
  o.pixel_noise_sigma = 0;
  o.depth_noise_k = 0;
  o.structured_light = true;
  SyntheticScene scene(MakeScene("handheld"), o);
  // Every reading is a depth of a disparity on the 1/8 px grid of a 580 px, 7.5 cm sensor.
  const double fb = 580 * 0.075;
  int readings = 0, missing_in_range = 0, off_grid = 0, far_hits = 0, close = 0, shadowed = 0, far_shadow_side = 0;
  for (size_t i = 0; i < 300; i += 30) {
    const Frame f = scene.Render(i);
    cv::Mat gray, exact;
    scene.RenderView(scene.PoseAt(scene.timestamp_ns(i) * 1e-9), 0, &gray, &exact);
    for (int v = 0; v < exact.rows; ++v) {
      for (int u = 0; u + 1 < exact.cols; ++u) {
        const float z = exact.at<float>(v, u + 1), d = f.depth.at<float>(v, u);  // registered 1 px off
        if (d > 0) {
          ++readings;
          const double steps = fb / d * 8;
          if (std::abs(steps - std::round(steps)) > 1e-3) ++off_grid;
          if (d > 4.5f + 0.05f) ++far_hits;
          if (z > 0 && std::abs(d - z) < 0.01 * z + z * z / fb / 8) ++close;
        } else if (z > 0 && z < 4.4f) {
          ++missing_in_range;
        }
        // The projector (7.5 cm to the camera's left) leaves a pixel unlit when a surface left of it
        // is nearer by more than their pixel distance in its parallax: past a step of over 3 / (fx b)
        // in inverse depth, and past the 2 pixels the nearer edge is fattened by (more where the edge
        // is slanted), a shadow at least 3 px wide starts within the next 4 pixels.
        const double fb_image = scene.calibration().camera.fx * 0.075;
        if (u >= 1 && u + 6 < exact.cols) {
          const float near = exact.at<float>(v, u - 1), far = exact.at<float>(v, u);
          bool flat = true;
          for (int k = 1; k <= 6; ++k) flat = flat && std::abs(exact.at<float>(v, u + k) - far) < 0.02f * far;
          if (near > 0 && far > 0 && far < 4.4f && 1 / near - 1 / far > 3 / fb_image && flat) {
            ++far_shadow_side;
            bool unlit = false;
            for (int k = 2; k <= 5; ++k) unlit = unlit || f.depth.at<float>(v, u + k - 1) == 0;  // reads exact u + k
            if (unlit) ++shadowed;
          }
        }
      }
    }
  }
  ASSERT_GT(readings, 200000);
  EXPECT_EQ(off_grid, 0);
  EXPECT_EQ(far_hits, 0);
  // Most readings are within quantization of the exact depth; edges and dropouts are the rest.
  EXPECT_GT(close, 0.9 * readings);
  EXPECT_GT(missing_in_range, 0.005 * readings);
  ASSERT_GT(far_shadow_side, 20);
  EXPECT_GT(shadowed, 0.8 * far_shadow_side);
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
    EXPECT_LT(
        (gt[i].T_world_cam.linear().transpose() * gt[i].T_world_cam.linear() - Eigen::Matrix3d::Identity()).norm(),
        1e-9);
  }
  // After one lap the camera is back near its start: a revisit.
  const double lap_s = scene.loop_length_m() / scene.description().agents[0].speed_mps;
  const size_t lap = static_cast<size_t>(lap_s * scene.options().frame_rate_hz);
  ASSERT_LT(lap, gt.size());
  EXPECT_LT((gt[lap].T_world_cam.translation() - gt[0].T_world_cam.translation()).head<2>().norm(), 0.1);
}

TEST(SyntheticScene, EveryPathIsSmooth) {
  // No kinks: the camera turns at most a few degrees between frames in every scene and agent
  // (hand-held glances turn at up to 3.5 rad/s: 7 degrees at 30 Hz).
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
      EXPECT_LT(worst, name == "handheld" ? 7.0 : 4.0) << name << " agent " << agent;
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

// A rig error moves the right image by that many pixels of disparity: the horizontal shift that
// best warps the left image into the right one (central columns, where a turned camera shifts
// every pixel alike) is -rig_error, and the exact rig's warp is off by it.
TEST(SyntheticScene, ARigErrorAddsItsPixelsToEveryDisparity) {
  for (const double rig_error : {0.0, 0.4, -1.0}) {
    SyntheticOptions o = SmallOptions(Sensor::kStereo);
    o.pixel_noise_sigma = 0;
    o.rig_error_px = rig_error;
    SyntheticScene scene(MakeScene("street"), o);
    const size_t i = 101;
    const Eigen::Isometry3d T_left = scene.PoseAt(scene.timestamp_ns(i) * 1e-9);
    cv::Mat left, depth;
    scene.RenderView(T_left, 0, &left, &depth);
    const Frame f = scene.Render(i);
    EXPECT_EQ(cv::norm(f.left, left, cv::NORM_INF), 0.0) << "the left image does not change";
    const PinholeCamera& cam = scene.calibration().camera;
    const double bf = cam.fx * scene.calibration().baseline_m;
    auto warp_error = [&](double du) {
      std::vector<double> errors;
      for (int v = 4; v < left.rows - 4; v += 2) {
        for (int u = static_cast<int>(cam.cx - left.cols / 6.0); u < cam.cx + left.cols / 6.0; u += 2) {
          const float z = depth.at<float>(v, u);
          if (z <= 0) continue;
          const double ur = u - bf / z + du;
          if (ur < 1 || ur > f.right.cols - 2) continue;
          errors.push_back(std::abs(left.at<uint8_t>(v, u) - Bilinear(f.right, ur, v)));
        }
      }
      std::nth_element(errors.begin(), errors.begin() + errors.size() / 2, errors.end());
      return errors[errors.size() / 2];
    };
    double best_du = 0, best = 1e9;
    for (double du = -1.5; du <= 1.5 + 1e-9; du += 0.05) {
      if (const double e = warp_error(du); e < best) {
        best = e;
        best_du = du;
      }
    }
    std::printf("rig_error %+.1f px: best shift %+.2f px (median warp error %.2f), exact rig's %.2f\n", rig_error,
                best_du, best, warp_error(0));
    EXPECT_NEAR(best_du, -rig_error, 0.1);
    if (rig_error != 0) {
      EXPECT_GT(warp_error(0), best + 0.5) << "the exact rig's warp must be worse";
    }
  }
  std::string name;
  SyntheticOptions o;
  ParseSyntheticSpec("street:rig_error=-0.1", &name, &o);
  EXPECT_EQ(o.rig_error_px, -0.1);
  try {
    ParseSyntheticSpec("street:rig_error=6", &name, &o);
    ADD_FAILURE() << "rig_error=6 accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("rig_error"), std::string::npos) << e.what();
  }
}

// A lens the calibration leaves out (k1): the distorted image shows at c + f x (1 + k1 r^2) what
// the exact camera shows at c + f x, the forward model, away from the centre where the two differ
// by pixels; the centre itself does not move.
TEST(SyntheticScene, ALensTheCalibrationLeavesOutShowsEachPointWhereItsK1Puts) {
  SyntheticOptions o = SmallOptions(Sensor::kMonocular);
  o.pixel_noise_sigma = 0;
  SyntheticScene exact(MakeScene("street"), o);
  o.lens_k1 = 0.1;
  SyntheticScene lens(MakeScene("street"), o);
  const size_t i = 101;
  const cv::Mat ideal = exact.Render(i).left, seen = lens.Render(i).left;
  const PinholeCamera& cam = exact.calibration().camera;
  std::vector<double> as_model, as_pinhole;
  double widest_px = 0;
  for (double yu = -0.48; yu <= 0.48; yu += 0.02) {
    for (double xu = -0.64; xu <= 0.64; xu += 0.02) {
      const double d = 1 + o.lens_k1 * (xu * xu + yu * yu);
      const double u = cam.cx + cam.fx * xu, v = cam.cy + cam.fy * yu;
      const double ud = cam.cx + cam.fx * xu * d, vd = cam.cy + cam.fy * yu * d;
      if (ud < 1 || vd < 1 || ud > seen.cols - 2 || vd > seen.rows - 2) continue;
      const double moved = std::hypot(ud - u, vd - v);
      if (moved < 1.5) continue;  // the centre: both comparisons alike
      widest_px = std::max(widest_px, moved);
      as_model.push_back(std::abs(Bilinear(seen, ud, vd) - Bilinear(ideal, u, v)));
      as_pinhole.push_back(std::abs(Bilinear(seen, u, v) - Bilinear(ideal, u, v)));
    }
  }
  ASSERT_GT(as_model.size(), 200u);
  EXPECT_GT(widest_px, 3.0);
  auto mean = [](const std::vector<double>& e) { return std::accumulate(e.begin(), e.end(), 0.0) / e.size(); };
  std::printf("k1 %.2f: %zu samples moved 1.5-%.1f px, mean difference %.2f grey levels as the model puts them, "
              "%.2f where a pinhole would\n",
              o.lens_k1, as_model.size(), widest_px, mean(as_model), mean(as_pinhole));
  EXPECT_LT(mean(as_model), 1.5);
  EXPECT_GT(mean(as_pinhole), 3 * mean(as_model));
  EXPECT_EQ(seen.at<uint8_t>(static_cast<int>(cam.cy), static_cast<int>(cam.cx)),
            ideal.at<uint8_t>(static_cast<int>(cam.cy), static_cast<int>(cam.cx)));

  std::string name;
  SyntheticOptions parsed;
  ParseSyntheticSpec("street:k1=0.02", &name, &parsed);
  EXPECT_EQ(parsed.lens_k1, 0.02);
  for (const char* bad : {"street:k1=-0.01", "street:k1=0.2"}) {
    try {
      ParseSyntheticSpec(bad, &name, &parsed);
      ADD_FAILURE() << bad << " accepted";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("k1="), std::string::npos) << e.what();
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
  EXPECT_THROW(ParseSyntheticSpec("room:dynamic=0.5", &scene, &o), Error);
  EXPECT_THROW(ParseSyntheticSpec("room:dynamic=-0.1", &scene, &o), Error);
  try {
    ParseSyntheticSpec("room:dynamic=0.4", &scene, &o);
    ADD_FAILURE() << "dynamic=0.4 accepted";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("dynamic"), std::string::npos) << e.what();
  }
  ParseSyntheticSpec("town:agent=2,duration=5,sensor=rgbd", &scene, &o);
  EXPECT_EQ(scene, "town");
  EXPECT_EQ(o.agent, 2);
  EXPECT_EQ(o.duration_s, 5);
  EXPECT_EQ(o.sensor, Sensor::kRgbd);
  o.agent = 3;
  EXPECT_THROW(SyntheticScene(MakeScene("town"), o), Error);
  SyntheticOptions bad;
  bad.width = 16;
  EXPECT_FALSE(bad.Check());
  EXPECT_THROW(SyntheticScene(MakeScene("room"), bad), Error);
}

// Spec as the command line and the dataset reader see it.
SyntheticOptions Parse(const std::string& spec, std::string* scene) {
  SyntheticOptions o;
  ParseSyntheticSpec(spec, scene, &o);
  return o;
}

double Median(std::vector<double> values) {
  if (values.empty()) return 0;
  std::nth_element(values.begin(), values.begin() + values.size() / 2, values.end());
  return values[values.size() / 2];
}

// Angular speed between consecutive ground-truth poses, rad/s.
std::vector<double> AngularSpeeds(const Trajectory& gt) {
  std::vector<double> speeds;
  for (size_t i = 1; i < gt.size(); ++i) {
    const double dt = (gt[i].t_ns - gt[i - 1].t_ns) * 1e-9;
    speeds.push_back(
        Eigen::AngleAxisd(gt[i - 1].T_world_cam.linear().transpose() * gt[i].T_world_cam.linear()).angle() / dt);
  }
  return speeds;
}

// Mean squared horizontal and vertical intensity difference: how much fine detail an image holds.
double GradientEnergy(const cv::Mat& gray) {
  cv::Mat f, dx, dy;
  gray.convertTo(f, CV_32F);
  cv::Sobel(f, dx, CV_32F, 1, 0);
  cv::Sobel(f, dy, CV_32F, 0, 1);
  return cv::mean(dx.mul(dx) + dy.mul(dy))[0];
}

TEST(SyntheticScene, SceneCameraDefaultsAndSpecOverrides) {
  std::string scene;
  {
    const SyntheticScene highway(MakeScene("highway"), Parse("highway", &scene));
    const Calibration& c = highway.calibration();
    EXPECT_EQ(c.camera.width, 1241);
    EXPECT_EQ(c.camera.height, 376);
    EXPECT_EQ(c.camera.fx, 718);
    EXPECT_EQ(c.camera.fy, 718);
    EXPECT_EQ(c.frame_rate_hz, 10);
    EXPECT_EQ(c.baseline_m, 0.54);
    EXPECT_EQ(highway.frame_count(), 600u);
  }
  {
    // Keys override; a new width alone keeps the field of view.
    const SyntheticOptions o = Parse("highway:width=620,fps=20,baseline=0.3,duration=5", &scene);
    const SyntheticScene highway(MakeScene(scene), o);
    const Calibration& c = highway.calibration();
    EXPECT_EQ(c.camera.width, 620);
    EXPECT_EQ(c.camera.height, 376);
    EXPECT_NEAR(c.camera.fx, 718.0 * 620 / 1241, 1e-9);
    EXPECT_EQ(c.frame_rate_hz, 20);
    EXPECT_EQ(c.baseline_m, 0.3);
    EXPECT_EQ(highway.frame_count(), 100u);
    const SyntheticScene narrow(MakeScene(scene), Parse("highway:fx=500,height=200,duration=1", &scene));
    EXPECT_EQ(narrow.calibration().camera.fx, 500);
  }
  {
    const SyntheticScene handheld(MakeScene("handheld"), Parse("handheld:duration=2", &scene));
    EXPECT_EQ(handheld.calibration().camera.width, 640);
    EXPECT_EQ(handheld.calibration().camera.height, 480);
    EXPECT_EQ(handheld.calibration().frame_rate_hz, 30);
    EXPECT_EQ(handheld.calibration().baseline_m, 0.1);
    EXPECT_EQ(handheld.frame_count(), 60u);
  }
  // The other scenes keep the general defaults.
  const SyntheticScene room(MakeScene("room"), Parse("room", &scene));
  EXPECT_EQ(room.calibration().camera.width, 640);
  EXPECT_EQ(room.calibration().camera.height, 480);
  EXPECT_EQ(room.calibration().camera.fx, 480);
  EXPECT_EQ(room.calibration().frame_rate_hz, 20);
  EXPECT_EQ(room.frame_count(), 1200u);
}

TEST(SceneMover, PoseInterpolatesWrapsAndRepeats) {
  SceneMover mover;
  mover.keys = {{0.0, {0, 0, 0}, 3.0}, {1.0, {2, 0, 0}, -3.0}};  // heading crosses +-pi
  const Eigen::Isometry3d half = mover.PoseAt(0.5);
  EXPECT_NEAR((half.translation() - Eigen::Vector3d(1, 0, 0)).norm(), 0, 1e-12);
  EXPECT_NEAR(std::abs(std::remainder(std::atan2(half.linear()(1, 0), half.linear()(0, 0)) - M_PI, 2 * M_PI)), 0, 1e-12)
      << "the short way round: through pi, not 0";
  EXPECT_NEAR((mover.PoseAt(7).translation() - Eigen::Vector3d(2, 0, 0)).norm(), 0, 1e-12) << "held at the end";
  EXPECT_NEAR(mover.PoseAt(-3).translation().norm(), 0, 1e-12) << "held at the start";
  mover.period_s = 2;  // back to the first key over [1, 2)
  EXPECT_NEAR((mover.PoseAt(1.5).translation() - Eigen::Vector3d(1, 0, 0)).norm(), 0, 1e-12);
  EXPECT_NEAR((mover.PoseAt(4.5).translation() - Eigen::Vector3d(1, 0, 0)).norm(), 0, 1e-12);
  EXPECT_NEAR((mover.PoseAt(-1.5).translation() - Eigen::Vector3d(1, 0, 0)).norm(), 0, 1e-12);
  mover.active_from_s = 1;
  mover.active_until_s = 2;
  EXPECT_FALSE(mover.active(0.5));
  EXPECT_TRUE(mover.active(1.5));
}

TEST(SyntheticHighway, DrivesAtMotorwaySpeedOnALoopLongerThanTheRun) {
  std::string scene;
  const SyntheticScene highway(MakeScene("highway"), Parse("highway:sensor=mono", &scene));
  const Trajectory gt = highway.GroundTruth();
  double slowest = 1e9, fastest = 0, height = 0;
  for (size_t i = 1; i < gt.size(); ++i) {
    const double speed = (gt[i].T_world_cam.translation() - gt[i - 1].T_world_cam.translation()).norm() /
                         ((gt[i].t_ns - gt[i - 1].t_ns) * 1e-9);
    slowest = std::min(slowest, speed);
    fastest = std::max(fastest, speed);
    height += gt[i].T_world_cam.translation().z() / gt.size();
  }
  std::printf("highway: %.1f-%.1f m/s, camera %.2f m above the road, %.0f m of a %.0f m loop\n", slowest, fastest,
              height, highway.path_length_m(), highway.loop_length_m());
  EXPECT_GT(slowest, 20.0);
  EXPECT_LT(fastest, 30.0);
  EXPECT_NEAR(height, 1.65, 0.05);
  EXPECT_LT(highway.path_length_m(), highway.loop_length_m()) << "60 s must not complete the loop";
  // Gentle curves: radius several hundred metres, so at most 25 / 300 rad/s of turning.
  const std::vector<double> turn = AngularSpeeds(gt);
  EXPECT_LT(*std::max_element(turn.begin(), turn.end()), 25.0 / 300);
  EXPECT_GT(*std::max_element(turn.begin(), turn.end()), 25.0 / 500) << "no curve at all";
}

TEST(SyntheticHighway, MostTextureIsFarWithTheRoadNearAndSkyAbove) {
  std::string scene;
  const SyntheticScene highway(MakeScene("highway"), Parse("highway:width=620,height=188,sensor=mono", &scene));
  const int W = highway.calibration().camera.width, H = highway.calibration().camera.height;
  std::vector<double> textured, road, above;
  double sky_top = 0, top_pixels = 0;
  for (double t = 5; t < 60; t += 10) {
    cv::Mat gray, depth;
    highway.RenderView(highway.PoseAt(t), t, 0, &gray, &depth);
    for (int v = 0; v < H; ++v) {
      for (int u = 0; u < W; ++u) {
        const float z = depth.at<float>(v, u);
        if (v < H / 5) {
          top_pixels += 1;
          sky_top += z <= 0;
        }
        if (z <= 0) continue;
        textured.push_back(z);
        if (v > H * 3 / 4 && std::abs(u - W / 2) < W / 8) road.push_back(z);  // just ahead, below the horizon
        if (v < H / 2) above.push_back(z);
      }
    }
  }
  const double median = Median(textured), road_median = Median(road), above_median = Median(above);
  std::printf(
      "highway depth: median %.1f m over textured pixels, road ahead %.1f m, above the horizon %.1f m, "
      "sky %.0f%% of the top rows\n",
      median, road_median, above_median, 100 * sky_top / top_pixels);
  EXPECT_GT(median, 20.0);
  EXPECT_LT(median, 200.0);
  EXPECT_LT(road_median, 15.0);
  EXPECT_LT(road_median, 0.5 * median);
  EXPECT_GT(above_median, median);
  EXPECT_GT(sky_top / top_pixels, 0.5) << "open sky above";
}

TEST(SyntheticHighway, TrafficMovesWhileTheCameraStandsStill) {
  std::string scene;
  const SyntheticOptions o = Parse("highway:width=620,height=188,duration=30,noise=0", &scene);
  const SyntheticScene highway(MakeScene(scene), o);
  SceneDescription parked = MakeScene(scene);
  parked.movers.clear();
  const SyntheticScene empty(parked, o);
  // At 20 s the camera is about to pass a truck in the right lane.
  const Eigen::Isometry3d T = highway.PoseAt(20);
  cv::Mat a, b, c, d;
  highway.RenderView(T, 20, 0, &a, nullptr);
  highway.RenderView(T, 20.5, 0, &b, nullptr);
  empty.RenderView(T, 20, 0, &c, nullptr);
  empty.RenderView(T, 20.5, 0, &d, nullptr);
  const double changed = cv::countNonZero(a != b) / static_cast<double>(a.total());
  std::printf("highway: %.1f%% of the pixels change in 0.5 s with the camera held still\n", 100 * changed);
  EXPECT_GT(changed, 0.01);
  EXPECT_EQ(cv::countNonZero(c != d), 0) << "without vehicles the world is static";
  EXPECT_GT(cv::countNonZero(a != c), 0);
  // Render() shows both eyes the vehicles at the frame's time.
  const size_t i = 200;
  const double t = highway.timestamp_ns(i) * 1e-9;
  const Frame f = highway.Render(i);
  cv::Mat left, right;
  highway.RenderView(highway.PoseAt(t), t, 0, &left, nullptr);
  highway.RenderView(highway.PoseAt(t) * Eigen::Translation3d(highway.calibration().baseline_m, 0, 0), t, 0, &right,
                     nullptr);
  EXPECT_EQ(cv::norm(f.left, left, cv::NORM_INF), 0.0);
  EXPECT_EQ(cv::norm(f.right, right, cv::NORM_INF), 0.0);
}

TEST(SyntheticScene, DynamicObjectsCoverAtMostTheirFraction) {
  std::string scene;
  const SyntheticOptions o = Parse("room:width=320,height=240,duration=14,noise=0,dynamic=0.3", &scene);
  SyntheticOptions plain = o;
  plain.dynamic_fraction = 0;
  const SyntheticScene dynamic(MakeScene(scene), o), still(MakeScene(scene), plain);
  EXPECT_GE(dynamic.description().movers.size(), 2u);
  double largest = 0;
  size_t busy = 0;
  for (size_t i = 0; i < dynamic.frame_count(); ++i) {
    const double t = dynamic.timestamp_ns(i) * 1e-9;
    ASSERT_TRUE(dynamic.PoseAt(t).isApprox(still.PoseAt(t), 0)) << "the camera's path stays the same";
    for (double offset : {0.0, dynamic.calibration().baseline_m}) {
      const Eigen::Isometry3d T = dynamic.PoseAt(t) * Eigen::Translation3d(offset, 0, 0);
      cv::Mat gray, depth_dynamic, depth_still;
      dynamic.RenderView(T, t, 0, &gray, &depth_dynamic);
      still.RenderView(T, t, 0, &gray, &depth_still);
      const double covered = cv::countNonZero(depth_dynamic != depth_still) / static_cast<double>(gray.total());
      largest = std::max(largest, covered);
      busy += covered > 0.05;
    }
  }
  std::printf("dynamic=0.3: objects cover up to %.1f%% of the image, more than 5%% in %zu views\n", 100 * largest,
              busy);
  EXPECT_LE(largest, 0.3);
  EXPECT_GT(largest, 0.1);
  // F = 0 leaves a scene bit-identical.
  const SyntheticScene zero(MakeScene(scene), Parse("room:width=320,height=240,duration=14,dynamic=0", &scene));
  const SyntheticScene none(MakeScene(scene), Parse("room:width=320,height=240,duration=14", &scene));
  EXPECT_EQ(zero.description().movers.size(), 0u);
  EXPECT_EQ(cv::norm(zero.Render(100).left, none.Render(100).left, cv::NORM_INF), 0.0);
}

TEST(SyntheticHandheld, FastGlancesAtWalkingPaceOnALoop) {
  std::string scene;
  const SyntheticScene handheld(MakeScene("handheld"), Parse("handheld:sensor=mono", &scene));
  const Trajectory gt = handheld.GroundTruth();
  std::vector<double> turn = AngularSpeeds(gt);
  const double peak = *std::max_element(turn.begin(), turn.end()), median = Median(turn);
  size_t fast = 0;
  for (double w : turn) fast += w > 2.0;
  const double speed = handheld.description().agents[0].speed_mps;
  std::printf("handheld: angular speed median %.2f rad/s, peak %.2f rad/s, %zu frames above 2 rad/s; %.1f m/s\n",
              median, peak, fast, speed);
  EXPECT_GT(peak, 2.5);
  EXPECT_LT(peak, 3.5);
  EXPECT_LT(median, 1.0) << "quick glances, not a constant spin";
  EXPECT_GT(fast, 20u) << "peaks come back";
  EXPECT_GT(speed, 0.5);
  EXPECT_LT(speed, 1.5);
  // The camera comes back to where it started: loops to close.
  const size_t lap = static_cast<size_t>(handheld.loop_length_m() / speed * handheld.options().frame_rate_hz);
  ASSERT_LT(3 * lap, gt.size());
  for (size_t k = 1; k <= 3; ++k)
    EXPECT_LT((gt[k * lap].T_world_cam.translation() - gt[0].T_world_cam.translation()).norm(), 0.15) << "lap " << k;
}

TEST(SyntheticHandheld, EveryFrameSeesCloseTexture) {
  std::string scene;
  const SyntheticScene handheld(MakeScene("handheld"), Parse("handheld:width=320,height=240,sensor=mono", &scene));
  std::vector<double> medians;
  for (size_t i = 0; i < handheld.frame_count(); i += 9) {
    const double t = handheld.timestamp_ns(i) * 1e-9;
    cv::Mat gray, depth;
    handheld.RenderView(handheld.PoseAt(t), t, 0, &gray, &depth);
    std::vector<double> z;
    for (int v = 0; v < depth.rows; ++v)
      for (int u = 0; u < depth.cols; ++u)
        if (depth.at<float>(v, u) > 0) z.push_back(depth.at<float>(v, u));
    ASSERT_GT(z.size(), 0.999 * depth.total()) << "frame " << i << " sees past the walls";
    cv::Scalar mean, stddev;
    cv::meanStdDev(gray, mean, stddev);
    ASSERT_GT(stddev[0], 25.0) << "frame " << i;
    medians.push_back(Median(z));
  }
  std::sort(medians.begin(), medians.end());
  const double typical = medians[medians.size() / 2];
  std::printf("handheld: median depth per frame %.2f-%.2f m, typically %.2f m\n", medians.front(), medians.back(),
              typical);
  EXPECT_GT(medians.front(), 0.5);
  EXPECT_LT(typical, 3.0);
  EXPECT_LT(medians.back(), 4.5) << "the room's long diagonal";
}

TEST(SyntheticHandheld, MotionBlurFollowsTheMotion) {
  std::string scene;
  const SyntheticOptions o = Parse("handheld:sensor=mono,noise=0,duration=30", &scene);
  const SyntheticScene blurred(MakeScene(scene), o);
  SceneDescription instant = MakeScene(scene);
  instant.exposure.exposure_s = 0;
  const SyntheticScene sharp(instant, o);
  const std::vector<double> turn = AngularSpeeds(blurred.GroundTruth());
  const size_t fastest = std::max_element(turn.begin(), turn.end()) - turn.begin() + 1;
  const size_t slowest = std::min_element(turn.begin(), turn.end()) - turn.begin() + 1;
  const Frame fast = blurred.Render(fastest), slow = blurred.Render(slowest);
  const double fast_ratio = GradientEnergy(fast.left) / GradientEnergy(sharp.Render(fastest).left);
  const double slow_ratio = GradientEnergy(slow.left) / GradientEnergy(sharp.Render(slowest).left);
  std::printf("handheld: gradient energy with blur / without: %.2f at %.2f rad/s, %.2f at %.2f rad/s\n", fast_ratio,
              turn[fastest - 1], slow_ratio, turn[slowest - 1]);
  EXPECT_LT(fast_ratio, 0.85);
  EXPECT_GT(slow_ratio, 0.97);
  Frame again;
  std::thread([&] { again = blurred.Render(fastest); }).join();
  EXPECT_EQ(cv::norm(fast.left, again.left, cv::NORM_INF), 0.0) << "deterministic across threads";
}

TEST(SyntheticHandheld, ExposureGainShiftsTheBrightness) {
  std::string scene;
  const SyntheticOptions o = Parse("handheld:sensor=mono,width=320,height=240,noise=0", &scene);
  const SyntheticScene varying(MakeScene(scene), o);
  SceneDescription fixed_gain = MakeScene(scene);
  fixed_gain.exposure.gain_wobble = 0;
  fixed_gain.exposure.gain_step_every_s = 0;
  const SyntheticScene fixed(fixed_gain, o);
  double lowest = 1e9, highest = 0, biggest_step = 0;
  size_t darkest = 0;
  for (size_t i = 0; i < varying.frame_count(); ++i) {
    const double g = varying.GainAt(varying.timestamp_ns(i) * 1e-9);
    if (g < lowest) lowest = g, darkest = i;
    highest = std::max(highest, g);
    if (i > 0)
      biggest_step = std::max(biggest_step, std::abs(g / varying.GainAt(varying.timestamp_ns(i - 1) * 1e-9) - 1));
    ASSERT_EQ(fixed.GainAt(varying.timestamp_ns(i) * 1e-9), 1.0);
  }
  std::printf("handheld: gain %.2f-%.2f, largest change between frames %.0f%%\n", lowest, highest, 100 * biggest_step);
  EXPECT_LT(lowest, 0.85);
  EXPECT_GT(highest, 1.1);
  EXPECT_GT(biggest_step, 0.15) << "an auto-exposure step";
  EXPECT_LT(biggest_step, 0.45);
  // Gain scales the image before noise: the darkest frame is darker by its gain.
  const double ratio = cv::mean(varying.Render(darkest).left)[0] / cv::mean(fixed.Render(darkest).left)[0];
  EXPECT_NEAR(ratio, lowest, 0.02);
}

// The AVX2 paths (shading, and the gain, noise and rounding that finish each image) give the
// portable paths' bits: every scene at its own camera (the motorway's 1241 columns end rows
// between groups of eight), stereo and RGB-D (exact depth), with moving objects and image noise,
// one frame per second of a 10-s run and the frame of the fastest turn (where the hand-held scene
// blurs most).
TEST(SyntheticScene, VectorShadingGivesThePortablePathsBits) {
  if (!HasAvx2()) GTEST_SKIP() << "no AVX2 on this CPU: only the portable path runs";
  auto same_bits = [](const cv::Mat& a, const cv::Mat& b) {
    if (a.size() != b.size() || a.type() != b.type()) return false;
    for (int r = 0; r < a.rows; ++r)
      if (std::memcmp(a.ptr(r), b.ptr(r), a.cols * a.elemSize()) != 0) return false;
    return true;
  };
  for (const std::string& name : SyntheticSceneNames()) {
    for (const Sensor sensor : {Sensor::kStereo, Sensor::kRgbd}) {
      SyntheticOptions o;
      o.sensor = sensor;
      o.duration_s = 10;
      o.dynamic_fraction = 0.3;
      o.depth_noise_k = 0;
      SyntheticScene vector(MakeScene(name), o);
      o.use_avx2 = false;
      SyntheticScene portable(MakeScene(name), o);
      std::vector<size_t> frames;
      for (size_t i = 0; i < vector.frame_count(); i += static_cast<size_t>(vector.calibration().frame_rate_hz))
        frames.push_back(i);
      const std::vector<double> turn = AngularSpeeds(vector.GroundTruth());
      frames.push_back(std::max_element(turn.begin(), turn.end()) - turn.begin() + 1);
      for (const size_t i : frames) {
        SCOPED_TRACE(name + " " + SensorName(sensor) + " frame " + std::to_string(i));
        const Frame a = vector.Render(i), b = portable.Render(i);
        EXPECT_TRUE(same_bits(a.left, b.left));
        EXPECT_TRUE(
            same_bits(sensor == Sensor::kStereo ? a.right : a.depth, sensor == Sensor::kStereo ? b.right : b.depth));
      }
    }
  }
}

}  // namespace
}  // namespace flatslam
