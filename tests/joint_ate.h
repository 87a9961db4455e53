// Keyframe ATE of several agents after ONE alignment of all of them onto their ground truths:
// what "every agent in one frame" means for a merged map (a per-agent alignment would hide a
// misplaced agent). The tests' shorthand for EvaluateJointAte.
#pragma once

#include <vector>

#include "trajectory/metrics.h"

namespace flatslam::testing {

// gt[k] and est[k] are agent k's ground truth and estimate (associated by time).
inline std::vector<double> JointAte(const std::vector<Trajectory>& gt, const std::vector<Trajectory>& est,
                                    Alignment kind = Alignment::kSE3) {
  EvalOptions options;
  options.alignment = kind;
  std::vector<double> ate;
  for (const ErrorStats& s : EvaluateJointAte(gt, est, options).ate_m) ate.push_back(s.rmse);
  return ate;
}

}  // namespace flatslam::testing
