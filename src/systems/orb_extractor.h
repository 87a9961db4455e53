// ORB extraction: image pyramid, FAST per grid cell with a fallback threshold, quadtree spread of
// a per-level budget, intensity-centroid orientation and 256-bit steered BRIEF.
// Concurrency: an OrbExtractor is immutable after construction; Extract() is const and may be
// called from many threads at once. Inside, pyramid levels run in a tbb::parallel_for.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <opencv2/core/mat.hpp>

#include "systems/features.h"

namespace flatslam {

struct OrbOptions {
  int features = 1000;           // keypoints per image over all levels
  float scale_factor = 1.2f;     // between consecutive pyramid levels
  int levels = 8;                // pyramid levels
  int fast_threshold = 20;       // FAST threshold (grey levels)
  int min_fast_threshold = 7;    // used in a grid cell where fast_threshold finds nothing
  int cell_size = 30;            // pixels (at each level) of a FAST grid cell, about
  int edge_margin = 19;          // pixels (at each level) kept free at the border, >= 16 (radius 15 disc)
  // false: level i gets a share proportional to 1/scale_factor^i (ORB-SLAM2's series, level 0
  // gets 21.7% at 1.2 x 8); true: proportional to the level's area, 1/scale_factor^(2i) (32.3%).
  bool budget_by_area = false;
  double blur_sigma = 2.0;       // Gaussian blur before the BRIEF tests (pixels)
  int blur_kernel = 7;           // odd kernel size of that blur
  uint64_t pattern_seed = 0x0b5e55edull;  // generator of the 256 BRIEF test pairs

  [[nodiscard]] bool Check() const;
};

// The image pyramid one extraction worked on; level 0 shares the input image's pixels.
// Level i has size round(cols / scale_factor^i) x round(rows / scale_factor^i).
struct ImagePyramid {
  std::vector<cv::Mat> levels;  // CV_8UC1, unblurred

  // Maps level-0 pixel coordinates to level `level` (pixel centres aligned, as cv::resize).
  [[nodiscard]] Eigen::Vector2f ToLevel(const Eigen::Vector2f& uv0, int level) const;
  // Maps level coordinates back to level 0.
  [[nodiscard]] Eigen::Vector2f FromLevel(const Eigen::Vector2f& uv, int level) const;
};

class OrbExtractor {
 public:
  // Throws flatslam::Error when !options.Check().
  explicit OrbExtractor(const OrbOptions& options = OrbOptions());

  [[nodiscard]] const OrbOptions& options() const { return options_; }
  [[nodiscard]] const ScalePyramid& scales() const { return scales_; }
  // Target keypoint count per level before redistributing the shortfall of sparse levels.
  [[nodiscard]] const std::vector<int>& level_budget() const { return level_budget_; }
  // The 256 test pairs (x1, y1, x2, y2), offsets from the keypoint on an unrotated patch.
  [[nodiscard]] const std::vector<std::array<int8_t, 4>>& pattern() const { return pattern_; }

  // Builds the pyramid (levels()[0] shares gray). Throws on an empty or non-CV_8UC1 image.
  void BuildPyramid(const cv::Mat& gray, ImagePyramid* pyramid) const;

  // Extracts up to options().features keypoints with descriptors into *out (replacing its
  // content; right_u and depth are -1). Keypoints are ordered by level, then by position
  // inside the level. Deterministic whatever the number of threads. Throws flatslam::Error on
  // an empty or non-CV_8UC1 image.
  void Extract(const cv::Mat& gray, Keypoints* out) const;
  // As above, also returning the pyramid (needed by stereo matching).
  void Extract(const cv::Mat& gray, Keypoints* out, ImagePyramid* pyramid) const;

 private:
  OrbOptions options_;
  ScalePyramid scales_;
  std::vector<int> level_budget_;
  std::vector<std::array<int8_t, 4>> pattern_;
  std::vector<int> circle_half_width_;  // per row offset 0..15: half width of the orientation disc
};

}  // namespace flatslam
