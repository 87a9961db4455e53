// Keyframe ATE of several agents after ONE alignment of all of them onto their ground truths:
// what "every agent in one frame" means for a merged map (a per-agent alignment would hide a
// misplaced agent).
#pragma once

#include <vector>

#include "trajectory/metrics.h"

namespace flatslam::testing {

// gt[k] and est[k] are agent k's ground truth and estimate (associated by time).
inline std::vector<double> JointAte(const std::vector<Trajectory>& gt, const std::vector<Trajectory>& est,
                                    Alignment kind = Alignment::kSE3) {
  std::vector<Eigen::Vector3d> gt_positions, est_positions;
  std::vector<std::vector<Eigen::Isometry3d>> gt_poses(gt.size()), est_poses(gt.size());
  for (size_t k = 0; k < gt.size(); ++k) {
    for (const IndexPair& p : AssociateByTime(gt[k], est[k])) {
      gt_poses[k].push_back(gt[k][p.gt_index].T_world_cam);
      est_poses[k].push_back(est[k][p.est_index].T_world_cam);
      gt_positions.push_back(gt_poses[k].back().translation());
      est_positions.push_back(est_poses[k].back().translation());
    }
  }
  const AlignmentResult alignment = AlignUmeyama(gt_positions, est_positions, kind);
  std::vector<double> ate;
  for (size_t k = 0; k < gt.size(); ++k) {
    for (Eigen::Isometry3d& T : est_poses[k]) T = alignment.Apply(T);
    ate.push_back(ComputeAte(gt_poses[k], est_poses[k]).rmse);
  }
  return ate;
}

}  // namespace flatslam::testing
