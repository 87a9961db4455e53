// Keyframe ATE of several agents after ONE alignment of all of them onto their ground truths:
// what "every agent in one frame" means for a merged map (a per-agent alignment would hide a
// misplaced agent). The tests' shorthand for EvaluateJointAte.
#pragma once

#include <cmath>
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

// Per-agent errors pooled into one RMS, each agent's squared error weighted by its pose pairs:
// what one alignment of every agent's keyframes measures over all of them (JointAteResult::all_m),
// taken for errors measured per agent (each agent's own map, aligned alone).
inline double PooledRms(const std::vector<double>& rmse, const std::vector<size_t>& pairs) {
  double sum = 0, count = 0;
  for (size_t k = 0; k < rmse.size() && k < pairs.size(); ++k) {
    sum += rmse[k] * rmse[k] * static_cast<double>(pairs[k]);
    count += static_cast<double>(pairs[k]);
  }
  return count > 0 ? std::sqrt(sum / count) : 0.0;
}

}  // namespace flatslam::testing
