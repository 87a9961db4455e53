// Stereo and RGB-D depth for keypoints: descriptor matching along rectified rows with SAD
// sub-pixel refinement (stereo), or a look-up in a registered depth image (RGB-D). Both fill
// Keypoints::right_u and Keypoints::depth so later systems treat the two sensors alike.
// Concurrency: free functions, no shared state; each call writes only its output keypoints
// (MatchStereo runs a tbb::parallel_for over the left keypoints inside).
#pragma once

#include <cmath>
#include <string>

#include <opencv2/core/mat.hpp>

#include "frontend/features.h"
#include "frontend/orb_extractor.h"
#include "core/option_fields.h"

namespace flatslam {

// Stereo matching's options: X(type, name, default, requirement, description) (core/option_fields.h).
#define FLATSLAM_STEREO_OPTIONS(X)                                                                                     \
  X(double, min_depth_m, 0, min_depth_m >= 0, "nearest accepted depth; 0 = one baseline (max disparity = fx)")         \
  X(int, descriptor_threshold, 75, descriptor_threshold >= 1 && descriptor_threshold <= 257,                           \
    "Hamming distance accepted when below (mean of 100 and 50)")                                                       \
  X(float, row_radius, 2.0f, row_radius >= 0,                                                                          \
    "candidate rows: |v_right - v_left| <= row_radius x scale of the right keypoint's octave")                         \
  X(int, octave_radius, 1, octave_radius >= 0, "candidate octaves: |octave_right - octave_left| <= octave_radius")     \
  X(int, sad_half_window, 5, sad_half_window >= 1 && sad_half_window <= 15,                                            \
    "SAD patch (2w+1)^2 on the left keypoint's pyramid level")                                                         \
  X(int, sad_search_radius, 5, sad_search_radius >= 1 && sad_search_radius <= 64,                                      \
    "level pixels searched either side of the descriptor match")                                                       \
  X(float, outlier_factor, 2.1f, outlier_factor > 0, "drop matches whose SAD exceeds factor x median SAD (1.5 x 1.4)") \
  X(double, disparity_offset_px, 0, std::abs(disparity_offset_px) <= 5,                                                \
    "pixels the rig adds to every disparity (its rectification error), taken off each match; `flatslam run` "          \
    "prints the offset its map measures")

struct StereoOptions {
  FLATSLAM_STEREO_OPTIONS(FLATSLAM_OPTION_FIELD)
  // Not settable by name: a test switch.
  bool use_avx2 = true;  // where the CPU has it; false forces the baseline kernels (same output)

  FLATSLAM_OPTION_MEMBERS(FLATSLAM_STEREO_OPTIONS)
  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const { return FieldsProblem(); }
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
