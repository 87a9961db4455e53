// Timestamped poses: the unit of ground truth, estimates and trajectory files.
// Concurrency: plain values.
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

namespace flatslam {

struct TimedPose {
  int64_t t_ns = 0;
  Eigen::Isometry3d T_world_cam = Eigen::Isometry3d::Identity();
};

using Trajectory = std::vector<TimedPose>;

}  // namespace flatslam
