#include "systems/orb_extractor.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgproc.hpp>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "io/image_io.h"
#include "io/synthetic.h"
#include "systems/features.h"
#include "test_data.h"

namespace flatslam {
namespace {

cv::Mat KittiImage() {
  return ReadGrayImage(testing::DatasetsDir() / "kitti/sequences/07/image_0/000000.png");
}

cv::Mat SyntheticImage(size_t frame = 40) {
  SyntheticOptions options;
  options.sensor = Sensor::kMonocular;
  SyntheticScene scene(MakeScene("room"), options);
  return scene.Render(frame).left;
}

OrbExtractor MakeExtractor(int features) {
  OrbOptions options;
  options.features = features;
  return OrbExtractor(options);
}

double AngleDifference(double a, double b) {
  double d = std::fmod(a - b, 2 * M_PI);
  if (d > M_PI) d -= 2 * M_PI;
  if (d < -M_PI) d += 2 * M_PI;
  return d;
}

// Index of b's descriptor nearest to d (first on ties).
int NearestDescriptor(const Descriptor& d, const Keypoints& b, int* distance) {
  int best = -1;
  *distance = 257;
  for (size_t j = 0; j < b.size(); ++j) {
    const int h = Hamming(d, b.descriptor[j]);
    if (h < *distance) {
      *distance = h;
      best = static_cast<int>(j);
    }
  }
  return best;
}

struct Repeatability {
  int considered = 0;   // keypoints of a whose warped position lies well inside b
  int correct = 0;      // nearest descriptor in b within 2 px (at its level) and at the expected octave
  int angle_ok = 0;     // of the correct ones, angle difference within 10 degrees of the expected one
};

// Matches a's keypoints to b's by brute force; `warp` maps a level-0 point of a to b,
// `expected_angle` gives the orientation of a's direction in b, octave_shift = octave_a - octave_b.
template <class Warp, class Angle>
Repeatability Measure(const Keypoints& a, const Keypoints& b, const ScalePyramid& scales, const cv::Size& b_size,
                      Warp warp, Angle expected_angle, int octave_shift) {
  Repeatability r;
  for (size_t i = 0; i < a.size(); ++i) {
    const Eigen::Vector2f p = warp(a.uv[i]);
    const int expected_octave = a.octave[i] - octave_shift;
    if (expected_octave < 0 || expected_octave >= scales.levels) continue;
    const float margin = 30 * scales.scale[expected_octave];
    if (p.x() < margin || p.y() < margin || p.x() > b_size.width - margin || p.y() > b_size.height - margin) continue;
    ++r.considered;
    int distance = 0;
    const int j = NearestDescriptor(a.descriptor[i], b, &distance);
    if (j < 0) continue;
    const float tolerance = 2.f * scales.scale[expected_octave];
    if ((b.uv[j] - p).norm() > tolerance || b.octave[j] != expected_octave) continue;
    ++r.correct;
    if (std::abs(AngleDifference(b.angle[j], expected_angle(a.angle[i]))) < 10 * M_PI / 180) ++r.angle_ok;
  }
  return r;
}

// Rotates by `degrees` counter-clockwise on screen about the centre (same canvas), and the
// matching point and angle maps.
struct Rotation {
  cv::Mat image;
  cv::Mat M;  // 2x3 CV_64F
  Eigen::Vector2f Apply(const Eigen::Vector2f& p) const {
    return {static_cast<float>(M.at<double>(0, 0) * p.x() + M.at<double>(0, 1) * p.y() + M.at<double>(0, 2)),
            static_cast<float>(M.at<double>(1, 0) * p.x() + M.at<double>(1, 1) * p.y() + M.at<double>(1, 2))};
  }
  float ApplyAngle(float angle) const {
    const double dx = M.at<double>(0, 0) * std::cos(angle) + M.at<double>(0, 1) * std::sin(angle);
    const double dy = M.at<double>(1, 0) * std::cos(angle) + M.at<double>(1, 1) * std::sin(angle);
    return static_cast<float>(std::atan2(dy, dx));
  }
};

Rotation Rotate(const cv::Mat& image, double degrees) {
  Rotation r;
  r.M = cv::getRotationMatrix2D(cv::Point2f((image.cols - 1) * 0.5f, (image.rows - 1) * 0.5f), degrees, 1.0);
  cv::warpAffine(image, r.image, r.M, image.size(), cv::INTER_LINEAR, cv::BORDER_CONSTANT, cv::Scalar(0));
  return r;
}

TEST(Hamming, MatchesNaiveBitCount) {
  std::mt19937_64 rng(7);
  for (int trial = 0; trial < 2000; ++trial) {
    Descriptor a, b;
    for (int w = 0; w < 4; ++w) {
      a[w] = rng();
      b[w] = trial % 3 == 0 ? a[w] ^ (uint64_t{1} << (rng() % 64)) : rng();
    }
    int naive = 0;
    for (int bit = 0; bit < 256; ++bit) naive += ((a[bit / 64] >> (bit % 64)) & 1) != ((b[bit / 64] >> (bit % 64)) & 1);
    ASSERT_EQ(Hamming(a, b), naive);
  }
  EXPECT_EQ(Hamming(Descriptor{}, Descriptor{~0ull, ~0ull, ~0ull, ~0ull}), 256);
}

TEST(ScalePyramid, LevelsScalesAndSigmas) {
  const ScalePyramid p = ScalePyramid::Make(8, 1.2f);
  ASSERT_EQ(p.scale.size(), 8u);
  EXPECT_FLOAT_EQ(p.scale[0], 1.f);
  EXPECT_NEAR(p.scale[7], std::pow(1.2, 7), 1e-4);
  for (int i = 0; i < 8; ++i) {
    EXPECT_NEAR(p.sigma2[i], p.scale[i] * p.scale[i], 1e-5);
    EXPECT_NEAR(p.inv_scale[i] * p.scale[i], 1.f, 1e-6);
    EXPECT_NEAR(p.inv_sigma2[i] * p.sigma2[i], 1.f, 1e-6);
  }
  EXPECT_THROW((void)ScalePyramid::Make(0, 1.2f), Error);
  EXPECT_THROW((void)ScalePyramid::Make(4, 1.0f), Error);
}

TEST(OrbExtractor, RejectsBadInputAndOptions) {
  const OrbExtractor orb;
  Keypoints kps;
  EXPECT_THROW(orb.Extract(cv::Mat(), &kps), Error);
  EXPECT_THROW(orb.Extract(cv::Mat(100, 100, CV_8UC3, cv::Scalar::all(0)), &kps), Error);
  EXPECT_THROW(orb.Extract(cv::Mat(100, 100, CV_32FC1, cv::Scalar::all(0)), &kps), Error);
  OrbOptions bad;
  bad.min_fast_threshold = 30;  // above fast_threshold
  EXPECT_FALSE(bad.Check());
  EXPECT_THROW(OrbExtractor{bad}, Error);
  bad = OrbOptions();
  bad.edge_margin = 10;  // the orientation disc would leave the image
  EXPECT_THROW(OrbExtractor{bad}, Error);
  EXPECT_TRUE(OrbOptions().Check());
}

TEST(OrbExtractor, TinyAndFlatImagesGiveFewOrNoKeypoints) {
  const OrbExtractor orb;
  Keypoints kps;
  orb.Extract(cv::Mat(20, 20, CV_8UC1, cv::Scalar(0)), &kps);
  EXPECT_EQ(kps.size(), 0u);
  orb.Extract(cv::Mat(200, 300, CV_8UC1, cv::Scalar(128)), &kps);
  EXPECT_EQ(kps.size(), 0u);
  EXPECT_TRUE(kps.consistent());
}

TEST(OrbExtractor, LevelBudgetsFollowTheGeometricSeries) {
  const OrbExtractor orb = MakeExtractor(1000);
  const std::vector<int>& budget = orb.level_budget();
  ASSERT_EQ(budget.size(), 8u);
  int sum = 0;
  for (int b : budget) sum += b;
  EXPECT_EQ(sum, 1000);
  EXPECT_NEAR(budget[0], 217, 1);  // 1000 (1 - 1/1.2) / (1 - 1.2^-8)
  for (int i = 1; i < 8; ++i) EXPECT_NEAR(budget[i] * 1.2, budget[i - 1], 2);
}

TEST(OrbExtractor, FillsTheBudgetOnKitti) {
  const cv::Mat img = KittiImage();
  ASSERT_EQ(img.size(), cv::Size(1226, 370));
  const OrbExtractor orb = MakeExtractor(2000);
  Keypoints kps;
  ImagePyramid pyramid;
  orb.Extract(img, &kps, &pyramid);
  ASSERT_TRUE(kps.consistent());
  EXPECT_GE(kps.size(), 1950u);
  EXPECT_LE(kps.size(), 2000u);
  std::vector<int> per_level(8, 0);
  for (size_t i = 0; i < kps.size(); ++i) {
    ASSERT_LT(kps.octave[i], 8);
    ++per_level[kps.octave[i]];
    const float margin = 19 * orb.scales().scale[kps.octave[i]] - 1;
    EXPECT_GE(kps.uv[i].x(), margin);
    EXPECT_GE(kps.uv[i].y(), margin);
    EXPECT_LE(kps.uv[i].x(), img.cols - margin);
    EXPECT_LE(kps.uv[i].y(), img.rows - margin);
    EXPECT_EQ(kps.right_u[i], -1.f);
    EXPECT_EQ(kps.depth[i], -1.f);
    EXPECT_GE(kps.angle[i], -M_PI - 1e-6);
    EXPECT_LE(kps.angle[i], M_PI + 1e-6);
  }
  std::printf("KITTI 07 #0: %zu keypoints, per level:", kps.size());
  for (int n : per_level) std::printf(" %d", n);
  std::printf("\n");
  for (int l = 0; l < 8; ++l) EXPECT_GT(per_level[l], 0) << "level " << l;
  EXPECT_GT(per_level[0], per_level[7]);
  // Keypoint positions map back to integer pixels of their level.
  for (size_t i = 0; i < kps.size(); i += 37) {
    const Eigen::Vector2f p = pyramid.ToLevel(kps.uv[i], kps.octave[i]);
    EXPECT_NEAR(p.x(), std::round(p.x()), 1e-3);
    EXPECT_NEAR(p.y(), std::round(p.y()), 1e-3);
  }
}

TEST(OrbExtractor, FillsTheBudgetOnSyntheticFrames) {
  const OrbExtractor orb = MakeExtractor(1000);
  Keypoints kps;
  for (size_t frame : {10u, 80u, 200u}) {
    orb.Extract(SyntheticImage(frame), &kps);
    EXPECT_GE(kps.size(), 950u) << "frame " << frame;
    EXPECT_LE(kps.size(), 1000u);
  }
}

// Counts keypoints in each cell of a 4x4 grid over the image.
std::vector<int> GridCounts(const Keypoints& kps, const cv::Size& size) {
  std::vector<int> cells(16, 0);
  for (const Eigen::Vector2f& uv : kps.uv) {
    const int cx = std::clamp(static_cast<int>(uv.x() * 4 / size.width), 0, 3);
    const int cy = std::clamp(static_cast<int>(uv.y() * 4 / size.height), 0, 3);
    ++cells[cy * 4 + cx];
  }
  return cells;
}

TEST(OrbExtractor, SpreadsKeypointsOverTheImage) {
  {
    const cv::Mat img = SyntheticImage();
    Keypoints kps;
    MakeExtractor(1000).Extract(img, &kps);
    const std::vector<int> cells = GridCounts(kps, img.size());
    for (int c = 0; c < 16; ++c) EXPECT_GE(cells[c], 20) << "synthetic cell " << c;
    EXPECT_LE(*std::max_element(cells.begin(), cells.end()), 0.15 * kps.size());
  }
  {
    const cv::Mat img = KittiImage();
    Keypoints kps;
    MakeExtractor(2000).Extract(img, &kps);
    const std::vector<int> cells = GridCounts(kps, img.size());
    std::printf("KITTI 4x4 grid:");
    for (int c : cells) std::printf(" %d", c);
    std::printf("\n");
    EXPECT_EQ(std::count(cells.begin(), cells.end(), 0), 0);
    EXPECT_GE(std::count_if(cells.begin(), cells.end(), [](int n) { return n >= 40; }), 14);
    EXPECT_LE(*std::max_element(cells.begin(), cells.end()), 0.15 * kps.size());
  }
}

void ExpectIdentical(const Keypoints& a, const Keypoints& b) {
  ASSERT_EQ(a.size(), b.size());
  for (size_t i = 0; i < a.size(); ++i) {
    ASSERT_EQ(a.uv[i], b.uv[i]) << i;
    ASSERT_EQ(a.angle[i], b.angle[i]) << i;
    ASSERT_EQ(a.octave[i], b.octave[i]) << i;
    ASSERT_EQ(a.response[i], b.response[i]) << i;
    ASSERT_EQ(a.descriptor[i], b.descriptor[i]) << i;
  }
}

TEST(OrbExtractor, DeterministicAcrossRunsAndThreadCounts) {
  const cv::Mat img = KittiImage();
  const OrbExtractor orb = MakeExtractor(2000);
  Keypoints reference, other;
  tbb::task_arena(1).execute([&] { orb.Extract(img, &reference); });
  orb.Extract(img, &other);
  ExpectIdentical(reference, other);
  tbb::task_arena(2).execute([&] { orb.Extract(img, &other); });
  ExpectIdentical(reference, other);
  tbb::task_arena(8).execute([&] { orb.Extract(img, &other); });  // oversubscribed
  ExpectIdentical(reference, other);
  // A second extractor with the same options draws the same pattern.
  MakeExtractor(2000).Extract(img, &other);
  ExpectIdentical(reference, other);
}

TEST(OrbExtractor, PatternIsValidAndSeeded) {
  const OrbExtractor orb;
  const auto& pattern = orb.pattern();
  ASSERT_EQ(pattern.size(), 256u);
  for (const auto& p : pattern) {
    EXPECT_LE(p[0] * p[0] + p[1] * p[1], 13 * 13);
    EXPECT_LE(p[2] * p[2] + p[3] * p[3], 13 * 13);
    EXPECT_FALSE(p[0] == p[2] && p[1] == p[3]);
  }
  OrbOptions other;
  other.pattern_seed = 12345;
  EXPECT_NE(OrbExtractor(other).pattern(), pattern);
}

TEST(OrbExtractor, DescriptorBitsAreInformative) {
  Keypoints kps;
  MakeExtractor(2000).Extract(KittiImage(), &kps);
  ASSERT_GT(kps.size(), 1000u);
  int balanced = 0;
  for (int bit = 0; bit < 256; ++bit) {
    size_t ones = 0;
    for (const Descriptor& d : kps.descriptor) ones += (d[bit / 64] >> (bit % 64)) & 1;
    const double mean = static_cast<double>(ones) / kps.size();
    balanced += mean > 0.2 && mean < 0.8;
  }
  EXPECT_GE(balanced, 230);
  double mean_distance = 0;
  int pairs = 0;
  for (size_t i = 0; i + 1 < kps.size(); i += 2, ++pairs) mean_distance += Hamming(kps.descriptor[i], kps.descriptor[i + 1]);
  mean_distance /= pairs;
  std::printf("bits with 0.2 < mean < 0.8: %d, mean distance of unrelated pairs %.1f\n", balanced, mean_distance);
  EXPECT_GT(mean_distance, 95);
}

TEST(OrbExtractor, AngleConventionPointsToTheBrightMass) {
  // A bright square on dark: at its top-left corner the bright mass lies towards +x, +y
  // (image y points down), so the angle is about +45 degrees; at the bottom-right corner -135.
  cv::Mat img(240, 320, CV_8UC1, cv::Scalar(30));
  cv::rectangle(img, cv::Rect(100, 80, 120, 90), cv::Scalar(220), cv::FILLED);
  Keypoints kps;
  MakeExtractor(200).Extract(img, &kps);
  bool saw_top_left = false, saw_bottom_right = false;
  for (size_t i = 0; i < kps.size(); ++i) {
    if (kps.octave[i] != 0) continue;
    if ((kps.uv[i] - Eigen::Vector2f(100, 80)).norm() < 2.5f) {
      saw_top_left = true;
      EXPECT_NEAR(AngleDifference(kps.angle[i], M_PI / 4), 0, 0.15);
    }
    if ((kps.uv[i] - Eigen::Vector2f(219, 169)).norm() < 2.5f) {
      saw_bottom_right = true;
      EXPECT_NEAR(AngleDifference(kps.angle[i], -3 * M_PI / 4), 0, 0.15);
    }
  }
  EXPECT_TRUE(saw_top_left);
  EXPECT_TRUE(saw_bottom_right);
}

TEST(OrbExtractor, RepeatableUnderRotation) {
  const OrbExtractor orb = MakeExtractor(1000);
  const cv::Mat img = SyntheticImage();
  Keypoints a;
  orb.Extract(img, &a);
  for (double degrees : {30.0, 90.0}) {
    const Rotation rot = Rotate(img, degrees);
    Keypoints b;
    orb.Extract(rot.image, &b);
    const Repeatability r = Measure(
        a, b, orb.scales(), rot.image.size(), [&](const Eigen::Vector2f& p) { return rot.Apply(p); },
        [&](float angle) { return rot.ApplyAngle(angle); }, 0);
    const double correct = static_cast<double>(r.correct) / r.considered;
    const double angle_ok = static_cast<double>(r.angle_ok) / std::max(1, r.correct);
    std::printf("synthetic rotated %.0f deg: %d considered, %.1f%% nearest descriptor correct, %.1f%% of those "
                "with angle within 10 deg\n", degrees, r.considered, 100 * correct, 100 * angle_ok);
    EXPECT_GT(r.considered, 200);
    EXPECT_GT(correct, 0.45) << degrees;
    EXPECT_GT(angle_ok, 0.9) << degrees;
  }
}

TEST(OrbExtractor, RepeatableUnderExactQuarterTurnOnKitti) {
  // cv::rotate permutes pixels exactly, so only the grid and the quadtree see a different image.
  const OrbExtractor orb = MakeExtractor(2000);
  const cv::Mat img = KittiImage();
  cv::Mat turned;
  cv::rotate(img, turned, cv::ROTATE_90_COUNTERCLOCKWISE);  // (x, y) -> (y, W - 1 - x)
  Keypoints a, b;
  orb.Extract(img, &a);
  orb.Extract(turned, &b);
  const float w = static_cast<float>(img.cols);
  const Repeatability r = Measure(
      a, b, orb.scales(), turned.size(), [&](const Eigen::Vector2f& p) { return Eigen::Vector2f(p.y(), w - 1 - p.x()); },
      [&](float angle) { return static_cast<float>(angle - M_PI / 2); }, 0);
  const double correct = static_cast<double>(r.correct) / r.considered;
  const double angle_ok = static_cast<double>(r.angle_ok) / std::max(1, r.correct);
  std::printf("KITTI quarter turn: %d considered, %.1f%% correct, %.1f%% with angle within 10 deg\n", r.considered,
              100 * correct, 100 * angle_ok);
  EXPECT_GT(correct, 0.5);
  EXPECT_GT(angle_ok, 0.95);
}

TEST(OrbExtractor, RepeatableUnderScaleChange) {
  // Shrinking by 1.2^2 moves a structure two levels down the pyramid.
  const OrbExtractor orb = MakeExtractor(1000);
  const ScalePyramid& scales = orb.scales();
  for (const bool kitti : {false, true}) {
    const cv::Mat img = kitti ? KittiImage() : SyntheticImage();
    cv::Mat small;
    const double s = 1.44;
    const cv::Size small_size(static_cast<int>(std::lround(img.cols / s)), static_cast<int>(std::lround(img.rows / s)));
    cv::resize(img, small, small_size, 0, 0, cv::INTER_AREA);
    const float sx = static_cast<float>(img.cols) / small.cols, sy = static_cast<float>(img.rows) / small.rows;
    Keypoints a, b;
    orb.Extract(img, &a);
    orb.Extract(small, &b);
    const Repeatability r = Measure(
        a, b, scales, small.size(),
        [&](const Eigen::Vector2f& p) { return Eigen::Vector2f((p.x() + 0.5f) / sx - 0.5f, (p.y() + 0.5f) / sy - 0.5f); },
        [](float angle) { return angle; }, 2);
    const double correct = static_cast<double>(r.correct) / r.considered;
    const double angle_ok = static_cast<double>(r.angle_ok) / std::max(1, r.correct);
    std::printf("%s scaled by 1/1.44: %d considered, %.1f%% correct (two levels down), %.1f%% angle within 10 deg\n",
                kitti ? "KITTI" : "synthetic", r.considered, 100 * correct, 100 * angle_ok);
    EXPECT_GT(r.considered, 150);
    EXPECT_GT(correct, 0.35);
    EXPECT_GT(angle_ok, 0.9);
  }
}

}  // namespace
}  // namespace flatslam
