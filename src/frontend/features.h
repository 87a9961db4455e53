// Per-image keypoint data as parallel arrays, binary descriptors and the scale pyramid.
// Concurrency: plain values; a Keypoints is written by one system at a time and read freely.
#pragma once

#include <array>
#include <bit>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

#include "core/error.h"
#include "ecs/descriptor.h"

namespace flatslam {

// Descriptor (256-bit steered BRIEF, bit i at word i/64, bit i%64) lives with the map in
// ecs/descriptor.h; Hamming is its distance under the name the systems use.
[[nodiscard]] inline int Hamming(const Descriptor& a, const Descriptor& b) {
  return DescriptorDistance(a, b);
}

// Keypoints of one image, struct-of-arrays: element i of every column describes keypoint i.
struct Keypoints {
  std::vector<Eigen::Vector2f> uv;  // pixels, level-0 coordinates of the rectified image
  std::vector<float> angle;         // radians, direction of the intensity centroid
  std::vector<uint8_t> octave;      // pyramid level the keypoint was detected on
  std::vector<float> response;      // FAST score, larger is stronger
  std::vector<Descriptor> descriptor;
  std::vector<float> right_u;  // stereo / RGB-D: x in the right image, -1 = none
  std::vector<float> depth;    // metres, -1 = none

  [[nodiscard]] size_t size() const { return uv.size(); }
  [[nodiscard]] bool empty() const { return uv.empty(); }
  // Resizes every column; new keypoints have no stereo match and no depth.
  void resize(size_t n) {
    uv.resize(n, Eigen::Vector2f::Zero());
    angle.resize(n, 0.f);
    octave.resize(n, 0);
    response.resize(n, 0.f);
    descriptor.resize(n, Descriptor{});
    right_u.resize(n, -1.f);
    depth.resize(n, -1.f);
  }
  void clear() { resize(0); }
  void reserve(size_t n) {
    uv.reserve(n);
    angle.reserve(n);
    octave.reserve(n);
    response.reserve(n);
    descriptor.reserve(n);
    right_u.reserve(n);
    depth.reserve(n);
  }
  // Keeps keypoint i where keep[i] is non-zero, in order (keep has size() elements).
  void Keep(const std::vector<uint8_t>& keep) {
    FLATSLAM_CHECK(keep.size() == size(), "Keypoints::Keep: ", keep.size(), " flags for ", size(), " keypoints");
    size_t n = 0;
    for (size_t i = 0; i < keep.size(); ++i) {
      if (!keep[i]) continue;
      uv[n] = uv[i];
      angle[n] = angle[i];
      octave[n] = octave[i];
      response[n] = response[i];
      descriptor[n] = descriptor[i];
      right_u[n] = right_u[i];
      depth[n] = depth[i];
      ++n;
    }
    resize(n);
  }
  // True when all columns have the same length (a debug invariant).
  [[nodiscard]] bool consistent() const {
    const size_t n = uv.size();
    return angle.size() == n && octave.size() == n && response.size() == n && descriptor.size() == n &&
           right_u.size() == n && depth.size() == n;
  }
};

// Scales of the image pyramid: level i is the image shrunk by scale[i] = scale_factor^i.
// sigma2[i] = scale[i]^2 is the variance (in level-0 pixels^2) of a keypoint measured on level i,
// used for search radii and information matrices (information = inv_sigma2 * I).
struct ScalePyramid {
  int levels = 0;
  float scale_factor = 1;
  float log_scale_factor = 0;  // ln(scale_factor), for predicting a level from a distance ratio
  std::vector<float> scale, inv_scale, sigma2, inv_sigma2;

  // Throws flatslam::Error unless levels >= 1 and scale_factor > 1 (or levels == 1).
  [[nodiscard]] static ScalePyramid Make(int levels, float scale_factor) {
    FLATSLAM_CHECK(levels >= 1 && levels <= 32, "ScalePyramid: levels must be in [1, 32], got ", levels);
    FLATSLAM_CHECK(scale_factor > 1.f || levels == 1, "ScalePyramid: scale_factor must be > 1, got ", scale_factor);
    ScalePyramid p;
    p.levels = levels;
    p.scale_factor = scale_factor;
    p.log_scale_factor = std::log(scale_factor);
    for (int i = 0; i < levels; ++i) {
      const float s = i == 0 ? 1.f : p.scale.back() * scale_factor;
      p.scale.push_back(s);
      p.inv_scale.push_back(1.f / s);
      p.sigma2.push_back(s * s);
      p.inv_sigma2.push_back(1.f / (s * s));
    }
    return p;
  }
};

}  // namespace flatslam
