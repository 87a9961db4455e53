// Stereo and RGB-D depth for keypoints: descriptor matching along rectified rows with SAD
// sub-pixel refinement (stereo), or a look-up in a registered depth image (RGB-D). Both fill
// Keypoints::right_u and Keypoints::depth so later systems treat the two sensors alike.
// Concurrency: free functions, no shared state; each call writes only its output keypoints
// (MatchStereo runs a tbb::parallel_for over the left keypoints inside).
#pragma once

#include <string>

#include <opencv2/core/mat.hpp>

#include "frontend/features.h"
#include "frontend/orb_extractor.h"

namespace flatslam {

struct StereoOptions {
  double min_depth_m = 0;         // nearest accepted depth; 0 = one baseline (max disparity = fx)
  int descriptor_threshold = 75;  // Hamming distance accepted when below (mean of 100 and 50)
  float row_radius = 2.0f;        // candidate rows: |v_right - v_left| <= row_radius * scale(right octave)
  int octave_radius = 1;          // candidate octaves: |octave_right - octave_left| <= octave_radius
  int sad_half_window = 5;        // SAD patch (2w+1)^2 on the left keypoint's pyramid level
  int sad_search_radius = 5;      // level pixels searched either side of the descriptor match
  float outlier_factor = 2.1f;    // drop matches whose SAD exceeds factor * median SAD (1.5 * 1.4)
  bool use_avx2 = true;           // where the CPU has it; false forces the baseline kernels (same output)

  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const;
  [[nodiscard]] bool Check() const { return Problem().empty(); }
};

// What a MatchStereo call did, for logs and tests.
struct StereoStats {
  int descriptor_matches = 0;  // left keypoints with a right candidate under descriptor_threshold
  int refined = 0;             // of those, with a SAD minimum inside the search and a valid disparity
  int matched = 0;             // of those, kept after the median SAD test (right_u, depth set)
};

// Matches left keypoints to right keypoints (both from the same OrbExtractor, with the pyramids
// it returned) on rectified images; sets left->right_u (level-0 x in the right image, sub-pixel)
// and left->depth = fx * baseline / (u_left - right_u), -1 where unmatched. Throws
// flatslam::Error on invalid options, mismatched image sizes or pyramids, or fx/baseline <= 0.
StereoStats MatchStereo(const Keypoints& right, const ImagePyramid& left_pyramid, const ImagePyramid& right_pyramid,
                        const ScalePyramid& scales, double fx, double baseline_m, const StereoOptions& options,
                        Keypoints* left);

// RGB-D: depth (metres, CV_32FC1, 0 or non-finite = none) read at each keypoint's rounded pixel;
// right_u = u - fx * virtual_baseline_m / depth, as if a stereo camera had measured it.
// Returns how many keypoints got a depth. Throws flatslam::Error on a wrong image type.
int DepthFromImage(const cv::Mat& depth_m, double fx, double virtual_baseline_m, Keypoints* keypoints);

}  // namespace flatslam
