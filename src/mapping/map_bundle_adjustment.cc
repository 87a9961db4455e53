#include "mapping/map_bundle_adjustment.h"

#include <algorithm>
#include <unordered_map>

namespace flatslam {

void BuildMapBundleAdjustment(const Map& map, const CameraGeometry& geometry, const StereoDepthRule& stereo,
                              std::span<const KeyFrameHandle> free, KeyFrameHandle anchor, size_t min_observations,
                              MapBundleAdjustment* out) {
  out->Clear();
  BundleAdjustmentProblem& problem = out->problem;
  problem.camera = geometry.camera;
  problem.baseline_m = geometry.camera.fx > 0 ? geometry.bf / geometry.camera.fx : 0.0;
  struct PoseInfo {
    uint32_t index;
    double far_depth;
  };
  std::unordered_map<KeyFrameHandle, PoseInfo> poses;
  poses.reserve(free.size() * 2);
  auto add_pose = [&](KeyFrameHandle h, bool fixed) -> const PoseInfo& {
    const KeyFrame& kf = map.keyframe(h);
    const PoseInfo info{static_cast<uint32_t>(problem.poses.size()), stereo.FarDepth(kf.depth)};
    problem.poses.push_back({kf.T_cam_world, fixed || h == anchor});
    out->keyframes.push_back(h);
    return poses.emplace(h, info).first->second;
  };
  for (KeyFrameHandle h : free)
    if (map.keyframes().contains(h) && !poses.count(h)) add_pose(h, false);

  std::unordered_map<PointHandle, uint32_t> taken;
  const size_t free_count = out->keyframes.size();
  for (size_t k = 0; k < free_count; ++k) {
    for (PointHandle p : map.keyframe(out->keyframes[k]).points) {
      if (p.is_null() || taken.count(p)) continue;
      const MapPoint* point = map.points().try_get(p);
      if (!point || point->observations.size() < min_observations) continue;
      taken.emplace(p, static_cast<uint32_t>(out->points.size()));
      out->points.push_back(p);
      problem.points.push_back(point->position);
    }
  }
  for (size_t j = 0; j < out->points.size(); ++j) {
    for (const Observation& o : map.point(out->points[j]).observations) {
      auto pose = poses.find(o.keyframe);
      const PoseInfo& info = pose != poses.end() ? pose->second : add_pose(o.keyframe, true);  // outside: fixed
      const KeyFrame& kf = map.keyframe(o.keyframe);
      BundleAdjustmentObservation obs;
      obs.pose_index = info.index;
      obs.point_index = static_cast<uint32_t>(j);
      obs.uv = kf.uv[o.keypoint].cast<double>();
      obs.right_u = geometry.bf > 0
                        ? StereoDepthRule::RightU(kf.right_u[o.keypoint], kf.depth[o.keypoint], info.far_depth)
                        : -1.0;
      obs.inv_sigma2 = geometry.pyramid.inv_sigma2[kf.octave[o.keypoint]];
      problem.observations.push_back(obs);
    }
  }
}

size_t ApplyMapBundleAdjustment(const MapBundleAdjustment& ba, const BundleAdjustmentResult& result,
                                bool erase_outliers, Map* map) {
  const BundleAdjustmentProblem& problem = ba.problem;
  size_t erased = 0;
  if (erase_outliers) {
    for (size_t k = 0; k < problem.observations.size(); ++k) {
      if (!result.outlier[k]) continue;
      const BundleAdjustmentObservation& o = problem.observations[k];
      map->EraseObservation(ba.points[o.point_index], ba.keyframes[o.pose_index]);
      ++erased;
    }
  }
  for (size_t k = 0; k < problem.poses.size(); ++k) {
    if (problem.poses[k].fixed) continue;
    if (KeyFrame* kf = map->keyframes().try_get(ba.keyframes[k])) kf->T_cam_world = problem.poses[k].T_cam_world;
  }
  for (size_t j = 0; j < problem.points.size(); ++j)
    if (MapPoint* point = map->points().try_get(ba.points[j])) point->position = problem.points[j];
  return erased;
}

}  // namespace flatslam
