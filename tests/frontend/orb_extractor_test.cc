#include "frontend/orb_extractor.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numeric>
#include <random>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <tbb/task_arena.h>

#include "core/error.h"
#include "io/image_io.h"
#include "io/synthetic.h"
#include "frontend/features.h"
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
  int considered = 0;  // keypoints of a whose warped position lies well inside b
  int detected = 0;    // of those, with a keypoint of b near the warped position at the expected octave
  int correct = 0;     // nearest descriptor in b within 2 px (at its level) and at the expected octave
  int angle_ok = 0;    // of the correct ones, angle difference within 10 degrees of the expected one
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
    const float tolerance = 2.f * scales.scale[expected_octave];
    for (size_t k = 0; k < b.size(); ++k) {
      if (b.octave[k] == expected_octave && (b.uv[k] - p).norm() <= tolerance) {
        ++r.detected;
        break;
      }
    }
    int distance = 0;
    const int j = NearestDescriptor(a.descriptor[i], b, &distance);
    if (j < 0) continue;
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

TEST(FastScores, CornerSetsMatchOpenCvAtEveryThreshold) {
  // The vectorised score (fast path) against OpenCV's FAST-9 without suppression (reference).
  for (const cv::Mat& img : {KittiImage(), SyntheticImage()}) {
    cv::Mat scores;
    FastScores(img, &scores);
    for (int t : {7, 20, 45}) {
      std::vector<cv::KeyPoint> reference;
      cv::FAST(img, reference, t, false);
      cv::Mat expected(img.size(), CV_8UC1, cv::Scalar(0));
      for (const cv::KeyPoint& k : reference) expected.at<uint8_t>(cvRound(k.pt.y), cvRound(k.pt.x)) = 1;
      const cv::Mat ours = scores > t;
      // OpenCV skips a 3-pixel border, as FastScores does.
      const cv::Rect inner(3, 3, img.cols - 6, img.rows - 6);
      EXPECT_EQ(cv::countNonZero((ours(inner) / 255) != expected(inner)), 0) << "threshold " << t;
      EXPECT_EQ(cv::countNonZero(ours(inner)), static_cast<int>(reference.size())) << "threshold " << t;
    }
  }
  cv::Mat scores;
  EXPECT_THROW(FastScores(cv::Mat(), &scores), Error);
}

TEST(OrbExtractor, BlurMatchesOpenCvGaussian) {
  // Integer taps (sum 256) and two roundings against OpenCV's 7x7, sigma 2 blur (reference).
  const OrbExtractor orb;
  const cv::Mat img = KittiImage();
  cv::Mat ours, reference;
  orb.BlurLevel(img, &ours);
  cv::GaussianBlur(img, reference, cv::Size(7, 7), 2.0, 2.0, cv::BORDER_REFLECT_101);
  cv::Mat difference;
  cv::absdiff(ours, reference, difference);
  double max_difference = 0;
  cv::minMaxLoc(difference, nullptr, &max_difference);
  EXPECT_LE(max_difference, 2);
  EXPECT_LT(cv::mean(difference)[0], 0.2);
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
  OrbExtractor orb = MakeExtractor(2000);
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
  // Keypoint positions map back to integer pixels of their level by default; refined
  // (orb.subpixel), most lie off the corner's pixel, by at most half a pixel.
  for (size_t i = 0; i < kps.size(); i += 37) {
    const Eigen::Vector2f p = pyramid.ToLevel(kps.uv[i], kps.octave[i]);
    EXPECT_NEAR(p.x(), std::round(p.x()), 1e-3);
    EXPECT_NEAR(p.y(), std::round(p.y()), 1e-3);
  }
  OrbOptions refined_options;
  refined_options.features = 2000;
  refined_options.subpixel = true;
  orb = OrbExtractor(refined_options);
  orb.Extract(img, &kps, &pyramid);
  int off_pixel = 0;
  for (size_t i = 0; i < kps.size(); ++i) {
    const Eigen::Vector2f p = pyramid.ToLevel(kps.uv[i], kps.octave[i]);
    EXPECT_LE(std::abs(p.x() - std::round(p.x())), 0.5f + 1e-3f);
    EXPECT_LE(std::abs(p.y() - std::round(p.y())), 0.5f + 1e-3f);
    off_pixel += (p - p.array().round().matrix()).norm() > 1e-3f;
  }
  EXPECT_GT(off_pixel, static_cast<int>(kps.size()) / 2);
}

TEST(OrbExtractor, AreaBudgetFavoursFineLevels) {
  OrbOptions options;
  options.budget_by_area = true;
  const OrbExtractor orb(options);
  EXPECT_NEAR(orb.level_budget()[0], 323, 1);  // 1000 (1 - 1.44^-1) / (1 - 1.44^-8)
  for (int i = 1; i < 8; ++i) EXPECT_NEAR(orb.level_budget()[i] * 1.44, orb.level_budget()[i - 1], 2);
}

TEST(ImagePyramid, LevelCoordinatesRoundTrip) {
  const OrbExtractor orb;
  ImagePyramid pyramid;
  orb.BuildPyramid(KittiImage(), &pyramid);
  ASSERT_EQ(pyramid.levels.size(), 8u);
  EXPECT_EQ(pyramid.levels[1].size(), cv::Size(1022, 308));
  for (int l = 0; l < 8; ++l) {
    const Eigen::Vector2f p(123.25f, 77.5f);
    EXPECT_LT((pyramid.FromLevel(pyramid.ToLevel(p, l), l) - p).norm(), 1e-3f);
  }
  // Pixel centres align as in cv::resize: level pixel x covers level-0 [x s, (x + 1) s).
  const float s = 1226.f / pyramid.levels[3].cols;
  EXPECT_NEAR(pyramid.FromLevel(Eigen::Vector2f(0, 0), 3).x(), 0.5f * s - 0.5f, 1e-4f);
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
    EXPECT_LE(*std::max_element(cells.begin(), cells.end()), 0.2 * kps.size());
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
  // A second extractor with the same options draws the same pattern.
  MakeExtractor(2000).Extract(img, &other);
  ExpectIdentical(reference, other);
}

void ExpectValidPattern(const BriefPattern& pattern, size_t size) {
  ASSERT_EQ(pattern.size(), size);
  const int r2 = kBriefPatternRadius * kBriefPatternRadius;
  for (size_t k = 0; k < pattern.size(); ++k) {
    const auto& p = pattern[k];
    EXPECT_LE(p[0] * p[0] + p[1] * p[1], r2);
    EXPECT_LE(p[2] * p[2] + p[3] * p[3], r2);
    EXPECT_GE((p[0] - p[2]) * (p[0] - p[2]) + (p[1] - p[3]) * (p[1] - p[3]), 4);
    for (size_t j = 0; j < k; ++j) {
      const auto& q = pattern[j];
      ASSERT_FALSE(p == q || (p[0] == q[2] && p[1] == q[3] && p[2] == q[0] && p[3] == q[1])) << k << " repeats " << j;
    }
  }
}

TEST(OrbExtractor, VectorAndBaselineKernelsAgree) {
  // The AVX2 kernels (used where the CPU has them) against the portable baseline ones.
  OrbOptions baseline;
  baseline.features = 2000;
  baseline.use_avx2 = false;
  Keypoints fast, reference;
  for (const cv::Mat& img : {KittiImage(), SyntheticImage()}) {
    MakeExtractor(2000).Extract(img, &fast);
    OrbExtractor(baseline).Extract(img, &reference);
    ExpectIdentical(fast, reference);
  }
}

TEST(OrbExtractor, PatternsAreValidAndSeeded) {
  const OrbExtractor orb;
  EXPECT_EQ(orb.pattern(), LearnedBriefPattern());
  ExpectValidPattern(LearnedBriefPattern(), 256);
  const BriefPattern g = GaussianBriefPairs(12345, 256);
  ExpectValidPattern(g, 256);
  EXPECT_EQ(GaussianBriefPairs(12345, 256), g);
  EXPECT_NE(GaussianBriefPairs(12346, 256), g);
  OrbOptions other;
  other.pattern_seed = 12345;
  EXPECT_EQ(OrbExtractor(other).pattern(), g);
  // The learned pairs come from the documented pool.
  const BriefPattern pool = GaussianBriefPairs(kLearnedPatternPoolSeed, kLearnedPatternPoolSize);
  for (const auto& p : LearnedBriefPattern()) EXPECT_NE(std::find(pool.begin(), pool.end(), p), pool.end());
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
  EXPECT_GE(balanced, 190);
  double mean_distance = 0;
  int pairs = 0;
  for (size_t i = 0; i + 1 < kps.size(); i += 2, ++pairs)
    mean_distance += Hamming(kps.descriptor[i], kps.descriptor[i + 1]);
  mean_distance /= pairs;
  std::printf("bits with 0.2 < mean < 0.8: %d, mean distance of unrelated pairs %.1f\n", balanced, mean_distance);
  EXPECT_GT(mean_distance, 98);
  // The plain G II pattern is much less balanced: steering biases its tests.
  OrbOptions g2;
  g2.features = 2000;
  g2.pattern_seed = 1;
  Keypoints plain;
  OrbExtractor(g2).Extract(KittiImage(), &plain);
  double plain_distance = 0;
  for (size_t i = 0; i + 1 < plain.size(); i += 2)
    plain_distance += Hamming(plain.descriptor[i], plain.descriptor[i + 1]);
  plain_distance /= pairs;
  std::printf("mean distance of unrelated pairs with a plain G II pattern: %.1f\n", plain_distance);
  EXPECT_GT(mean_distance, plain_distance + 5);
}

TEST(OrbExtractor, AngleConventionPointsToTheBrightMass) {
  // A bright square on dark: at its top-left corner the bright mass lies towards +x, +y
  // (image y points down), so the angle is about +45 degrees; at the bottom-right corner -135.
  cv::Mat img(240, 320, CV_8UC1, cv::Scalar(30));
  cv::rectangle(img, cv::Rect(100, 80, 120, 90), cv::Scalar(220), cv::FILLED);
  // Soften: on a perfect step, neighbouring FAST scores tie and non-maximum suppression drops both.
  cv::GaussianBlur(img, img, cv::Size(5, 5), 1.0);
  Keypoints kps;
  MakeExtractor(200).Extract(img, &kps);
  bool saw_top_left = false, saw_bottom_right = false;
  for (size_t i = 0; i < kps.size(); ++i) {
    if (kps.octave[i] != 0) continue;
    if ((kps.uv[i] - Eigen::Vector2f(100, 80)).norm() < 3.f) {
      saw_top_left = true;
      EXPECT_NEAR(AngleDifference(kps.angle[i], M_PI / 4), 0, 0.15);
    }
    if ((kps.uv[i] - Eigen::Vector2f(219, 169)).norm() < 3.f) {
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
    const double score = static_cast<double>(r.correct) / std::max(1, r.detected);
    const double angle_ok = static_cast<double>(r.angle_ok) / std::max(1, r.correct);
    std::printf(
        "synthetic rotated %.0f deg: %d considered, %.1f%% re-detected, %.1f%% nearest descriptor correct "
        "(%.1f%% of re-detected), %.1f%% of those with angle within 10 deg\n",
        degrees, r.considered, 100.0 * r.detected / r.considered, 100 * correct, 100 * score, 100 * angle_ok);
    EXPECT_GT(r.considered, 200);
    EXPECT_GT(correct, 0.38) << degrees;
    EXPECT_GT(score, 0.85) << degrees;
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
      a, b, orb.scales(), turned.size(),
      [&](const Eigen::Vector2f& p) { return Eigen::Vector2f(p.y(), w - 1 - p.x()); },
      [&](float angle) { return static_cast<float>(angle - M_PI / 2); }, 0);
  const double correct = static_cast<double>(r.correct) / r.considered;
  const double angle_ok = static_cast<double>(r.angle_ok) / std::max(1, r.correct);
  std::printf(
      "KITTI quarter turn: %d considered, %.1f%% re-detected, %.1f%% correct, %.1f%% with angle within 10 "
      "deg\n",
      r.considered, 100.0 * r.detected / r.considered, 100 * correct, 100 * angle_ok);
  EXPECT_GT(correct, 0.7);
  EXPECT_GT(static_cast<double>(r.correct) / r.detected, 0.95);
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
        [&](const Eigen::Vector2f& p) {
          return Eigen::Vector2f((p.x() + 0.5f) / sx - 0.5f, (p.y() + 0.5f) / sy - 0.5f);
        },
        [](float angle) { return angle; }, 2);
    const double correct = static_cast<double>(r.correct) / r.considered;
    const double angle_ok = static_cast<double>(r.angle_ok) / std::max(1, r.correct);
    std::printf(
        "%s scaled by 1/1.44: %d considered, %.1f%% re-detected, %.1f%% correct (two levels down), %.1f%% "
        "angle within 10 deg\n",
        kitti ? "KITTI" : "synthetic", r.considered, 100.0 * r.detected / r.considered, 100 * correct, 100 * angle_ok);
    EXPECT_GT(r.considered, 150);
    EXPECT_GT(correct, 0.65);
    EXPECT_GT(static_cast<double>(r.correct) / r.detected, 0.9);
    EXPECT_GT(angle_ok, 0.9);
  }
}

// RMS distance (level-0 pixels) between the keypoints of a shifted copy and those of the image
// moved by the shift: each keypoint of `a` well inside, paired with the nearest one of `b` on its
// level within one level pixel. `b` is `a`'s image translated by (dx, dy) with bilinear sampling.
double ShiftError(const Keypoints& a, const Keypoints& b, const ScalePyramid& scales, const cv::Size& size,
                  float dx, float dy, int max_octave, int* pairs) {
  double sum = 0;
  *pairs = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    if (a.octave[i] > max_octave) continue;
    const Eigen::Vector2f p = a.uv[i] + Eigen::Vector2f(dx, dy);
    if (p.x() < 40 || p.y() < 40 || p.x() > size.width - 40 || p.y() > size.height - 40) continue;
    float best = scales.scale[a.octave[i]];
    for (size_t k = 0; k < b.size(); ++k) {
      if (b.octave[k] == a.octave[i]) best = std::min(best, (b.uv[k] - p).norm());
    }
    if (best >= scales.scale[a.octave[i]]) continue;
    sum += best * best;
    ++*pairs;
  }
  return std::sqrt(sum / std::max(1, *pairs));
}

TEST(OrbExtractor, SubpixelPositionsFollowAFractionalShift) {
  // The image and copies of it moved by fractions of a pixel: a keypoint found on both should lie
  // where the shift puts it. On integer positions the error is at least the quantization, 0.41 px
  // RMS over both axes (0.29 each); the refined positions follow the shift more closely (KITTI:
  // 0.51 -> 0.29 px, the room 0.54 -> 0.33 px).
  for (const bool kitti : {true, false}) {
    const cv::Mat img = kitti ? KittiImage() : SyntheticImage();
    double error[2] = {0, 0};
    int pairs[2] = {0, 0};
    for (const bool subpixel : {false, true}) {
      OrbOptions options;
      options.features = 2000;
      options.subpixel = subpixel;
      const OrbExtractor orb(options);
      Keypoints a;
      orb.Extract(img, &a);
      double sum = 0;
      for (const auto& [dx, dy] : {std::pair{0.25f, 0.f}, std::pair{0.5f, 0.25f}, std::pair{0.f, 0.5f}}) {
        const cv::Mat M = (cv::Mat_<double>(2, 3) << 1, 0, dx, 0, 1, dy);
        cv::Mat moved;
        cv::warpAffine(img, moved, M, img.size(), cv::INTER_LINEAR, cv::BORDER_REPLICATE);
        Keypoints b;
        orb.Extract(moved, &b);
        int n = 0;
        const double e = ShiftError(a, b, orb.scales(), img.size(), dx, dy, 0, &n);
        sum += e * e * n;
        pairs[subpixel] += n;
      }
      error[subpixel] = std::sqrt(sum / std::max(1, pairs[subpixel]));
    }
    std::printf("%s level 0, shifted by fractions of a pixel: RMS error %.3f px on integer positions (%d pairs), "
                "%.3f px refined (%d pairs)\n",
                kitti ? "KITTI" : "synthetic", error[0], pairs[0], error[1], pairs[1]);
    EXPECT_GT(pairs[0], 300);
    EXPECT_GT(pairs[1], 300);
    EXPECT_LT(error[1], 0.8 * error[0]);
  }
}

TEST(OrbExtractor, MatchesAcrossFramesWithKnownMotion) {
  // Frames f and f + 4 of the synthetic room: a's keypoints are moved into b with the exact
  // depth and poses; nearest descriptors under ORB-SLAM2's TH_LOW (50) should be right.
  SyntheticOptions options;
  options.sensor = Sensor::kMonocular;
  SyntheticScene scene(MakeScene("room"), options);
  const PinholeCamera& cam = scene.calibration().camera;
  const OrbExtractor orb = MakeExtractor(1000);
  int considered = 0, nearest_right = 0, accepted = 0, accepted_right = 0;
  for (size_t f : {20u, 100u, 200u, 300u}) {
    const Eigen::Isometry3d T_world_a = scene.PoseAt(scene.timestamp_ns(f) * 1e-9);
    const Eigen::Isometry3d T_world_b = scene.PoseAt(scene.timestamp_ns(f + 4) * 1e-9);
    cv::Mat gray, depth;
    scene.RenderView(T_world_a, 0, &gray, &depth);
    Keypoints a, b;
    orb.Extract(scene.Render(f).left, &a);
    orb.Extract(scene.Render(f + 4).left, &b);
    const Eigen::Isometry3d T_b_a = T_world_b.inverse() * T_world_a;
    for (size_t i = 0; i < a.size(); ++i) {
      const int x = static_cast<int>(std::lround(a.uv[i].x())), y = static_cast<int>(std::lround(a.uv[i].y()));
      const double z = depth.at<float>(y, x);
      if (z <= 0) continue;
      const Eigen::Vector3d X_b =
          T_b_a * Eigen::Vector3d((a.uv[i].x() - cam.cx) / cam.fx * z, (a.uv[i].y() - cam.cy) / cam.fy * z, z);
      if (X_b.z() < 0.1) continue;
      const Eigen::Vector2f p(cam.fx * X_b.x() / X_b.z() + cam.cx, cam.fy * X_b.y() / X_b.z() + cam.cy);
      if (p.x() < 20 || p.y() < 20 || p.x() > cam.width - 20 || p.y() > cam.height - 20) continue;
      ++considered;
      int distance = 0;
      const int j = NearestDescriptor(a.descriptor[i], b, &distance);
      const bool right = j >= 0 && (b.uv[j] - p).norm() < 3 * orb.scales().scale[a.octave[i]];
      nearest_right += right;
      if (distance <= 50) {
        ++accepted;
        accepted_right += right;
      }
    }
  }
  std::printf(
      "room frames 4 apart: %d considered, nearest descriptor right %.1f%%; distance <= 50: %d (%.1f%%), "
      "%.1f%% right\n",
      considered, 100.0 * nearest_right / considered, accepted, 100.0 * accepted / considered,
      100.0 * accepted_right / accepted);
  EXPECT_GT(nearest_right, 0.5 * considered);
  EXPECT_GT(accepted, 0.4 * considered);
  EXPECT_GT(accepted_right, 0.88 * accepted);
}

// Regenerates kLearnedPattern in src/frontend/orb_extractor.cc: prints the table (a minute).
// Run: build/tests/test_frontend --gtest_also_run_disabled_tests --gtest_filter=*LearnPattern
// Training keypoints (every third) from KITTI 06 left frames 0, 5, .., 50 and EuRoC V1_01 cam0 and
// cam1; the pool is GaussianBriefPairs(kLearnedPatternPoolSeed, kLearnedPatternPoolSize). As ORB's
// rBRIEF: order the pool by |mean - 1/2| of the steered test, keep a test when its correlation
// with every kept one is below a threshold, raise the threshold by 0.05 until 256 are kept.
TEST(OrbExtractor, DISABLED_LearnPattern) {
  const auto data = testing::DatasetsDir();
  std::vector<std::filesystem::path> files;
  for (int i = 0; i <= 50; i += 5) {
    char name[32];
    std::snprintf(name, sizeof(name), "%06d.png", i);
    files.push_back(data / "kitti/sequences/06/image_0" / name);
  }
  for (const char* cam : {"cam0", "cam1"}) {
    std::vector<std::filesystem::path> euroc;
    for (const auto& e : std::filesystem::directory_iterator(data / "euroc/V1_01_first20/mav0" / cam / "data")) {
      euroc.push_back(e.path());
    }
    std::sort(euroc.begin(), euroc.end());
    files.insert(files.end(), euroc.begin(), euroc.end());
  }

  OrbOptions options;
  options.features = 2000;
  options.pattern_seed = 1;  // any: only keypoints and angles are used
  const OrbExtractor orb(options);
  const int r = kBriefPatternRadius, side = 2 * r + 1;
  std::vector<int> disc_index(side * side, -1);
  std::vector<Eigen::Vector2f> disc;
  for (int y = -r; y <= r; ++y) {
    for (int x = -r; x <= r; ++x) {
      if (x * x + y * y > r * r) continue;
      disc_index[(y + r) * side + x + r] = static_cast<int>(disc.size());
      disc.emplace_back(static_cast<float>(x), static_cast<float>(y));
    }
  }
  // Steered, blurred intensities at every disc point, as the extractor samples them.
  std::vector<std::vector<uint8_t>> samples;
  const auto round = [](float v) { return static_cast<int>(v + 64.5f) - 64; };
  for (const auto& file : files) {
    Keypoints kps;
    ImagePyramid pyramid;
    orb.Extract(ReadGrayImage(file), &kps, &pyramid);
    std::vector<cv::Mat> blurred(pyramid.levels.size());
    for (size_t l = 0; l < blurred.size(); ++l) orb.BlurLevel(pyramid.levels[l], &blurred[l]);
    for (size_t i = 0; i < kps.size(); i += 3) {
      const int level = kps.octave[i];
      const Eigen::Vector2f q = pyramid.ToLevel(kps.uv[i], level);
      const int x = static_cast<int>(std::lround(q.x())), y = static_cast<int>(std::lround(q.y()));
      const float c = std::cos(kps.angle[i]), s = std::sin(kps.angle[i]);
      std::vector<uint8_t> v(disc.size());
      for (size_t d = 0; d < disc.size(); ++d) {
        const float px = disc[d].x(), py = disc[d].y();
        v[d] = blurred[level].at<uint8_t>(y + round(px * s + py * c), x + round(px * c - py * s));
      }
      samples.push_back(std::move(v));
    }
  }
  const size_t n = samples.size(), words = (n + 63) / 64;

  const BriefPattern pool = GaussianBriefPairs(kLearnedPatternPoolSeed, kLearnedPatternPoolSize);
  std::vector<std::vector<uint64_t>> bits(pool.size(), std::vector<uint64_t>(words, 0));
  std::vector<double> mean(pool.size());
  for (size_t t = 0; t < pool.size(); ++t) {
    const int i1 = disc_index[(pool[t][1] + r) * side + pool[t][0] + r];
    const int i2 = disc_index[(pool[t][3] + r) * side + pool[t][2] + r];
    size_t ones = 0;
    for (size_t k = 0; k < n; ++k) {
      if (samples[k][i1] < samples[k][i2]) {
        bits[t][k / 64] |= uint64_t{1} << (k % 64);
        ++ones;
      }
    }
    mean[t] = static_cast<double>(ones) / n;
  }
  std::vector<size_t> order(pool.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(),
                   [&](size_t a, size_t b) { return std::abs(mean[a] - 0.5) < std::abs(mean[b] - 0.5); });
  std::vector<size_t> kept;
  std::vector<uint8_t> used(pool.size(), 0);
  for (double threshold = 0.2; kept.size() < 256 && threshold < 1.0; threshold += 0.05) {
    for (size_t t : order) {
      if (used[t]) continue;
      bool independent = true;
      for (size_t u : kept) {
        size_t both = 0;
        for (size_t w = 0; w < words; ++w) both += std::popcount(bits[t][w] & bits[u][w]);
        const double p_ab = static_cast<double>(both) / n;
        const double corr =
            (p_ab - mean[t] * mean[u]) / std::sqrt(mean[t] * (1 - mean[t]) * mean[u] * (1 - mean[u]) + 1e-12);
        if (std::abs(corr) > threshold) {
          independent = false;
          break;
        }
      }
      if (!independent) continue;
      kept.push_back(t);
      used[t] = 1;
      if (kept.size() == 256) break;
    }
    std::printf("// correlation <= %.2f: %zu tests\n", threshold, kept.size());
  }
  ASSERT_EQ(kept.size(), 256u);
  std::printf("// %zu training keypoints from %zu images\n", n, files.size());
  for (size_t t : kept) std::printf("    {%d, %d, %d, %d},\n", pool[t][0], pool[t][1], pool[t][2], pool[t][3]);
}

}  // namespace
}  // namespace flatslam
