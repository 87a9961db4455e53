#include "frontend/stereo_matcher.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "io/image_io.h"
#include "io/synthetic.h"
#include "frontend/orb_extractor.h"
#include "test_data.h"

namespace flatslam {
namespace {

OrbExtractor MakeStereoExtractor(int features) {
  OrbOptions options;
  options.features = features;
  return OrbExtractor(options);
}

struct StereoFrame {
  Keypoints left, right;
  ImagePyramid left_pyramid, right_pyramid;
};

StereoFrame ExtractPair(const OrbExtractor& orb, const cv::Mat& left, const cv::Mat& right) {
  StereoFrame f;
  orb.Extract(left, &f.left, &f.left_pyramid);
  orb.Extract(right, &f.right, &f.right_pyramid);
  return f;
}

double Median(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

TEST(StereoOptions, Check) {
  EXPECT_TRUE(StereoOptions().Check());
  StereoOptions o;
  o.sad_half_window = 0;
  EXPECT_FALSE(o.Check());
  o = StereoOptions();
  o.outlier_factor = 0;
  EXPECT_FALSE(o.Check());
  o = StereoOptions();
  o.disparity_offset_px = 6;
  EXPECT_FALSE(o.Check());
}

TEST(MatchStereo, DepthsAgreeWithTheRendererOnSyntheticFrames) {
  SyntheticOptions options;
  options.sensor = Sensor::kStereo;
  SyntheticScene scene(MakeScene("room"), options);
  const Calibration& calib = scene.calibration();
  const OrbExtractor orb = MakeStereoExtractor(1000);
  int total = 0, matched = 0, within_3pct = 0, within_half_px = 0;
  for (size_t i : {5u, 60u, 150u, 300u}) {
    const Frame frame = scene.Render(i);
    StereoFrame f = ExtractPair(orb, frame.left, frame.right);
    const StereoStats stats = MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(), calib.camera.fx,
                                          calib.baseline_m, StereoOptions(), &f.left);
    cv::Mat gray, depth;
    scene.RenderView(scene.PoseAt(scene.timestamp_ns(i) * 1e-9), 0, &gray, &depth);
    int frame_matched = 0;
    for (size_t k = 0; k < f.left.size(); ++k) {
      ASSERT_EQ(f.left.depth[k] < 0, f.left.right_u[k] < 0);
      if (f.left.depth[k] < 0) continue;
      ++frame_matched;
      const int x = static_cast<int>(std::lround(f.left.uv[k].x())),
                y = static_cast<int>(std::lround(f.left.uv[k].y()));
      const double truth = depth.at<float>(y, x);
      ASSERT_GT(truth, 0);
      const double disparity = f.left.uv[k].x() - f.left.right_u[k];
      EXPECT_NEAR(f.left.depth[k], calib.camera.fx * calib.baseline_m / disparity, 1e-3 * f.left.depth[k]);
      const double true_disparity = calib.camera.fx * calib.baseline_m / truth;
      within_3pct += std::abs(f.left.depth[k] - truth) < 0.03 * truth;
      within_half_px += std::abs(disparity - true_disparity) < 0.5;
    }
    EXPECT_EQ(frame_matched, stats.matched);
    std::printf("synthetic frame %zu: %zu keypoints, %d descriptor matches, %d refined, %d matched\n", i, f.left.size(),
                stats.descriptor_matches, stats.refined, stats.matched);
    total += static_cast<int>(f.left.size());
    matched += frame_matched;
  }
  std::printf("synthetic: %d/%d matched (%.1f%%), %.1f%% within 3%% depth, %.1f%% within 0.5 px disparity\n", matched,
              total, 100.0 * matched / total, 100.0 * within_3pct / matched, 100.0 * within_half_px / matched);
  EXPECT_GT(matched, 0.5 * total);
  EXPECT_GT(within_3pct, 0.9 * matched);
  EXPECT_GT(within_half_px, 0.95 * matched);
}

TEST(MatchStereo, DeterministicAcrossThreadCounts) {
  SyntheticOptions options;
  SyntheticScene scene(MakeScene("room"), options);
  const Frame frame = scene.Render(20);
  const OrbExtractor orb = MakeStereoExtractor(1000);
  StereoFrame a = ExtractPair(orb, frame.left, frame.right);
  StereoFrame b = a;
  tbb::task_arena(1).execute([&] {
    (void)MatchStereo(a.right, a.left_pyramid, a.right_pyramid, orb.scales(), scene.calibration().camera.fx,
                      scene.calibration().baseline_m, StereoOptions(), &a.left);
  });
  tbb::task_arena(4).execute([&] {
    (void)MatchStereo(b.right, b.left_pyramid, b.right_pyramid, orb.scales(), scene.calibration().camera.fx,
                      scene.calibration().baseline_m, StereoOptions(), &b.left);
  });
  EXPECT_EQ(a.left.right_u, b.left.right_u);
  EXPECT_EQ(a.left.depth, b.left.depth);
}

TEST(MatchStereo, VectorAndBaselineKernelsAgree) {
  const auto dir = testing::DatasetsDir() / "kitti/sequences/06";
  const OrbExtractor orb = MakeStereoExtractor(2000);
  const StereoFrame pair =
      ExtractPair(orb, ReadGrayImage(dir / "image_0/000010.png"), ReadGrayImage(dir / "image_1/000010.png"));
  for (int w : {3, 5, 7}) {
    StereoFrame a = pair, b = pair;
    StereoOptions fast, baseline;
    fast.sad_half_window = baseline.sad_half_window = w;
    baseline.use_avx2 = false;
    const StereoStats sa =
        MatchStereo(a.right, a.left_pyramid, a.right_pyramid, orb.scales(), 707.0912, 0.537, fast, &a.left);
    const StereoStats sb =
        MatchStereo(b.right, b.left_pyramid, b.right_pyramid, orb.scales(), 707.0912, 0.537, baseline, &b.left);
    EXPECT_GT(sa.matched, 500) << w;
    EXPECT_EQ(sa.matched, sb.matched) << w;
    EXPECT_EQ(a.left.right_u, b.left.right_u) << w;
    EXPECT_EQ(a.left.depth, b.left.depth) << w;
  }
}

TEST(MatchStereo, RespectsMinimumDepth) {
  SyntheticOptions options;
  SyntheticScene scene(MakeScene("room"), options);
  const Frame frame = scene.Render(60);
  const OrbExtractor orb = MakeStereoExtractor(1000);
  StereoFrame f = ExtractPair(orb, frame.left, frame.right);
  StereoOptions o;
  o.min_depth_m = 3.0;
  const StereoStats stats = MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(),
                                        scene.calibration().camera.fx, scene.calibration().baseline_m, o, &f.left);
  EXPECT_GT(stats.matched, 0);
  for (float d : f.left.depth) {
    // The disparity gate applies to the refined x, so no depth is below the minimum.
    if (d >= 0) {
      EXPECT_GE(d, 3.0 * (1 - 1e-5));
    }
  }
}

// A rig that adds 0.4 px to every disparity (synthetic rig_error): matched as it is, depths come out
// near; with the offset set, the same matches give the renderer's depths again.
TEST(MatchStereo, ADisparityOffsetTakesARigErrorOff) {
  SyntheticOptions options;
  options.sensor = Sensor::kStereo;
  options.rig_error_px = 0.4;
  SyntheticScene scene(MakeScene("room"), options);
  const Calibration& calib = scene.calibration();
  const double bf = calib.camera.fx * calib.baseline_m;
  const OrbExtractor orb = MakeStereoExtractor(1000);
  cv::Mat gray, exact_depth;
  const double t = scene.timestamp_ns(60) * 1e-9;
  scene.RenderView(scene.PoseAt(t), t, 0, &gray, &exact_depth);
  const Frame frame = scene.Render(60);
  // Median of measured minus true disparity near the image centre, where the turned camera shifts
  // every pixel alike.
  auto median_error = [&](double offset) {
    StereoFrame f = ExtractPair(orb, frame.left, frame.right);
    StereoOptions o;
    o.disparity_offset_px = offset;
    (void)MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(), calib.camera.fx, calib.baseline_m, o,
                      &f.left);
    std::vector<double> errors;
    for (size_t i = 0; i < f.left.size(); ++i) {
      if (f.left.depth[i] < 0 || f.left.octave[i] > 2) continue;
      const Eigen::Vector2f uv = f.left.uv[i];
      if (std::abs(uv.x() - calib.camera.cx) > calib.camera.width / 6.0) continue;
      const float z =
          exact_depth.at<float>(static_cast<int>(std::lround(uv.y())), static_cast<int>(std::lround(uv.x())));
      if (z <= 0) continue;
      EXPECT_NEAR(f.left.depth[i], bf / (uv.x() - f.left.right_u[i]), 1e-3 * f.left.depth[i]);
      errors.push_back(uv.x() - f.left.right_u[i] - bf / z);
    }
    EXPECT_GT(errors.size(), 30u);
    return Median(errors);
  };
  const double as_is = median_error(0), corrected = median_error(0.4);
  std::printf("rig error 0.4 px: median disparity error %.3f px as matched, %.3f px with the offset set\n", as_is,
              corrected);
  EXPECT_NEAR(as_is, 0.4, 0.1);
  EXPECT_NEAR(corrected, 0.0, 0.1);
}

TEST(MatchStereo, RejectsBadInput) {
  const OrbExtractor orb = MakeStereoExtractor(300);
  cv::Mat img(120, 160, CV_8UC1);
  cv::randu(img, 0, 255);
  cv::Mat other(100, 160, CV_8UC1);
  cv::randu(other, 0, 255);
  StereoFrame f = ExtractPair(orb, img, other);
  EXPECT_THROW(
      (void)MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(), 500, 0.1, StereoOptions(), &f.left),
      Error);
  f = ExtractPair(orb, img, img);
  EXPECT_THROW(
      (void)MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(), 0, 0.1, StereoOptions(), &f.left),
      Error);
  StereoOptions bad;
  bad.sad_search_radius = 0;
  EXPECT_THROW((void)MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(), 500, 0.1, bad, &f.left),
               Error);
}

TEST(MatchStereo, PlausibleDepthsOnKitti06) {
  const auto dir = testing::DatasetsDir() / "kitti/sequences/06";
  const double fx = 707.0912, cy = 183.1104, baseline = 0.537;
  const OrbExtractor orb = MakeStereoExtractor(2000);
  for (const char* name : {"000000.png", "000025.png", "000050.png"}) {
    StereoFrame f = ExtractPair(orb, ReadGrayImage(dir / "image_0" / name), ReadGrayImage(dir / "image_1" / name));
    const StereoStats stats =
        MatchStereo(f.right, f.left_pyramid, f.right_pyramid, orb.scales(), fx, baseline, StereoOptions(), &f.left);
    std::vector<double> depths, ground_ratio;
    for (size_t k = 0; k < f.left.size(); ++k) {
      if (f.left.depth[k] < 0) continue;
      depths.push_back(f.left.depth[k]);
      // Below the horizon near the image centre line the road dominates: a flat ground 1.65 m
      // below the camera is at depth fx * 1.65 / (v - cy).
      const double v = f.left.uv[k].y(), u = f.left.uv[k].x();
      if (v > cy + 60 && std::abs(u - 610) < 200) ground_ratio.push_back(f.left.depth[k] / (fx * 1.65 / (v - cy)));
    }
    const double median = Median(depths);
    const double ratio = ground_ratio.size() > 10 ? Median(ground_ratio) : 0;
    std::printf(
        "KITTI 06 %s: %zu keypoints, %d descriptor matches, %d refined, %d matched; median depth %.1f m, "
        "min %.2f, max %.1f; road ratio %.2f over %zu\n",
        name, f.left.size(), stats.descriptor_matches, stats.refined, stats.matched, median,
        *std::min_element(depths.begin(), depths.end()), *std::max_element(depths.begin(), depths.end()), ratio,
        ground_ratio.size());
    EXPECT_GT(stats.matched, 700) << name;
    for (double d : depths) EXPECT_GE(d, baseline);
    EXPECT_GT(median, 5);
    EXPECT_LT(median, 40);
    EXPECT_GT(ratio, 0.8);
    EXPECT_LT(ratio, 1.25);
  }
}

TEST(DepthFromImage, ExactOnASyntheticDepthImage) {
  cv::Mat depth(60, 80, CV_32FC1);
  for (int y = 0; y < depth.rows; ++y) {
    for (int x = 0; x < depth.cols; ++x) depth.at<float>(y, x) = 1.0f + 0.01f * x + 0.1f * y;
  }
  depth.at<float>(10, 10) = 0;                                        // no measurement
  depth.at<float>(20, 20) = std::numeric_limits<float>::quiet_NaN();  // invalid
  Keypoints kps;
  kps.resize(6);
  kps.uv = {{5.4f, 7.6f}, {10.f, 10.f}, {20.2f, 19.8f}, {79.4f, 59.4f}, {-3.f, 4.f}, {30.6f, 80.f}};
  const double fx = 500, b = 0.08;
  EXPECT_EQ(DepthFromImage(depth, fx, b, &kps), 2);
  EXPECT_FLOAT_EQ(kps.depth[0], 1.0f + 0.01f * 5 + 0.1f * 8);
  EXPECT_FLOAT_EQ(kps.right_u[0], static_cast<float>(5.4 - fx * b / kps.depth[0]));
  EXPECT_FLOAT_EQ(kps.depth[3], 1.0f + 0.01f * 79 + 0.1f * 59);
  for (int k : {1, 2, 4, 5}) {
    EXPECT_EQ(kps.depth[k], -1.f) << k;
    EXPECT_EQ(kps.right_u[k], -1.f) << k;
  }
  EXPECT_THROW((void)DepthFromImage(cv::Mat(10, 10, CV_16UC1), fx, b, &kps), Error);
  EXPECT_THROW((void)DepthFromImage(depth, fx, 0, &kps), Error);
}

TEST(DepthFromImage, MatchesTheRenderedDepth) {
  SyntheticOptions options;
  options.sensor = Sensor::kRgbd;
  SyntheticScene scene(MakeScene("room"), options);
  const Frame frame = scene.Render(30);
  ASSERT_EQ(frame.depth.type(), CV_32FC1);
  Keypoints kps;
  MakeStereoExtractor(1000).Extract(frame.left, &kps);
  const double fx = scene.calibration().camera.fx, b = 0.08;
  const int n = DepthFromImage(frame.depth, fx, b, &kps);
  EXPECT_GT(n, 0.9 * kps.size());
  for (size_t k = 0; k < kps.size(); ++k) {
    const float d = frame.depth.at<float>(static_cast<int>(std::lround(kps.uv[k].y())),
                                          static_cast<int>(std::lround(kps.uv[k].x())));
    if (d > 0) {
      EXPECT_EQ(kps.depth[k], d);
      EXPECT_NEAR(kps.uv[k].x() - kps.right_u[k], fx * b / d, 1e-3);
    } else {
      EXPECT_EQ(kps.depth[k], -1.f);
    }
  }
}

}  // namespace
}  // namespace flatslam
