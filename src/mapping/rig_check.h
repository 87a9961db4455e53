// How far a stereo rig's measured disparities sit from where the map's points say they should be:
// a real rig's rectification error shifts every disparity by about the same fraction of a pixel
// (KITTI 06: about -0.1 px), which biases depths most where disparities are small. A map point
// seen by several keyframes is placed again from its left-image rays alone (no stereo), and each of
// its stereo observations gives measured minus predicted disparity; a weighted line
// residual = offset + slope * disparity, fitted with 3-sigma trimming, separates the constant
// offset (the rig) from a residual growing with disparity (a scale error of the map).
// Concurrency: reads the map; the caller keeps writers out while it runs.
#pragma once

#include <cstddef>
#include <string>

#include "ecs/map.h"
#include "geometry/camera.h"

namespace flatslam {

struct DisparityOffsetOptions {
  size_t min_observations = 3;   // keyframes that see a point, for its rays to place it
  double min_ray_angle_deg = 1;  // widest angle between those rays
  double pixel_sigma = 0.3;      // disparity noise at level 0, pixels (grows with the level's scale)
  int trim_iterations = 5;       // refits dropping residuals beyond 3 sigma
};

struct DisparityOffsetFit {
  bool ok = false;                 // enough observations (at least 100) for a fit
  double offset_px = 0;            // measured minus predicted disparity, constant part
  double offset_sigma_px = 0;      // its standard error
  double slope = 0;                // part proportional to the disparity (a scale error of the map)
  double median_disparity_px = 0;  // of those observations: an offset matters in proportion to it
  size_t observations = 0;         // stereo observations kept after trimming
  size_t points = 0;               // points placed from their rays
};

// Needs geometry.bf > 0 (stereo or RGB-D); a monocular map gives ok = false.
[[nodiscard]] DisparityOffsetFit FitDisparityOffset(const Map& map, const CameraGeometry& geometry,
                                                    const DisparityOffsetOptions& options = {});

// One line for a user: the offset with its noise, and the setting that takes it off (offset_set_px,
// what the map's run took off already, plus the fit; NaN when not known: what to add to it) when it
// is a rectification error worth
// correcting: beyond 3 sigma, above 0.05 px (a depth 1% at 5 px of disparity) and moving the median
// observation's depth 0.5% or more (near scenes with large disparities barely feel it, and there
// the map's scale takes it up instead). Empty when !fit.ok.
[[nodiscard]] std::string DescribeDisparityOffset(const DisparityOffsetFit& fit, double offset_set_px);

}  // namespace flatslam
