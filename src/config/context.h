// What every system of one session reads and none writes: the options resolved for the camera and
// what follows from the calibration (projection geometry, the stereo depth rule, map scales).
// Concurrency: built once with the session, then read-only on any thread.
#pragma once

#include "config/options.h"
#include "ecs/map.h"
#include "geometry/camera.h"
#include "io/calibration.h"

namespace flatslam {

struct SystemContext {
  Calibration calibration;
  SlamOptions options;  // resolved for the calibration (ResolvedOptions)
  CameraGeometry geometry;
  StereoDepthRule stereo_depth;  // which stereo observations optimization keeps as stereo
  MapScales map_scales;

  // Checks the resolved options (naming the field that fails) and the calibration; throws
  // flatslam::Error. `pyramid` is the extractor's scale pyramid.
  SystemContext(const Calibration& calibration, const SlamOptions& resolved, const ScalePyramid& pyramid);

  [[nodiscard]] bool monocular() const { return calibration.sensor == Sensor::kMonocular; }
  // The stereo or RGB-D virtual baseline in metres; 0 for a monocular camera.
  [[nodiscard]] double baseline_m() const { return geometry.bf / geometry.camera.fx; }
  // Depth below which a measured depth is reliable ("close" points): close_depth_baselines x
  // baseline; 0 for a monocular camera.
  [[nodiscard]] double CloseDepth() const {
    return monocular() ? 0.0 : options.close_depth_baselines * geometry.bf / geometry.camera.fx;
  }
};

}  // namespace flatslam
