// The end-to-end SLAM tests' score of an estimate against ground truth: ATE after SE(3) and after
// Sim(3) alignment, and the length of the true path the bars are fractions of.
#pragma once

#include "trajectory/metrics.h"
#include "trajectory/trajectory.h"

namespace flatslam::testing {

struct TrajectoryScore {
  EvalResult se3, sim3;
  double path_m = 0;
};

inline TrajectoryScore ScoreTrajectory(const Trajectory& ground_truth, const Trajectory& estimate) {
  TrajectoryScore score;
  EvalOptions eval;
  eval.alignment = Alignment::kSE3;
  score.se3 = Evaluate(ground_truth, estimate, eval);
  eval.alignment = Alignment::kSim3;
  score.sim3 = Evaluate(ground_truth, estimate, eval);
  for (size_t i = 1; i < ground_truth.size(); ++i)
    score.path_m += (ground_truth[i].T_world_cam.translation() - ground_truth[i - 1].T_world_cam.translation()).norm();
  return score;
}

}  // namespace flatslam::testing
