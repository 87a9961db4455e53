// The frame a reader delivers (images as cv::Mat), with the calibration and trajectory types
// shared by readers, renderer, writers and metrics.
// Concurrency: plain values.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>

#include <opencv2/core/mat.hpp>

#include "io/calibration.h"
#include "trajectory/trajectory.h"

namespace flatslam {

class RefinedCamera;  // io/orb_settings.h

// One input frame. left is CV_8UC1 (gray); right is CV_8UC1 for stereo;
// depth is CV_32FC1 in metres (0 = no measurement) for RGB-D.
struct Frame {
  size_t index = 0;
  int64_t t_ns = 0;
  cv::Mat left;
  cv::Mat right;
  cv::Mat depth;
  // Null: left is an image of the calibration's camera. Set by a monocular reader whose left
  // image is still the given camera's (ApplyCameraRefit): keypoints measured in it lie at
  // lens->FromGiven in the calibration's camera. Undistorting a frame's keypoints costs a small
  // part of undistorting its pixels.
  std::shared_ptr<const RefinedCamera> lens;
};

}  // namespace flatslam
