#include "mapping/map_bundle_adjustment.h"

#include <algorithm>
#include <cstdint>
#include <vector>

namespace flatslam {

void BuildMapBundleAdjustment(const Map& map, const CameraGeometry& geometry, const StereoDepthRule& stereo,
                              std::span<const KeyFrameHandle> free, KeyFrameHandle anchor, size_t min_observations,
                              MapBundleAdjustment* out) {
  out->Clear();
  BundleAdjustmentProblem& problem = out->problem;
  problem.camera = geometry.camera;
  problem.baseline_m = geometry.camera.fx > 0 ? geometry.bf / geometry.camera.fx : 0.0;
  // Problem pose of each live keyframe and whether a live point is taken, by arena slot (a live
  // handle owns its slot): the window can be a whole map.
  constexpr uint32_t kNone = UINT32_MAX;
  std::vector<uint32_t> pose_of_slot(map.keyframes().slot_count(), kNone);
  std::vector<double> far_depth;
  auto add_pose = [&](KeyFrameHandle h, bool fixed) {
    const KeyFrame& kf = map.keyframe(h);
    pose_of_slot[h.index()] = static_cast<uint32_t>(problem.poses.size());
    far_depth.push_back(stereo.FarDepth(kf.depth));
    problem.poses.push_back({kf.T_cam_world, fixed || h == anchor});
    out->keyframes.push_back(h);
    return pose_of_slot[h.index()];
  };
  for (KeyFrameHandle h : free)
    if (map.keyframes().contains(h) && pose_of_slot[h.index()] == kNone) add_pose(h, false);

  std::vector<uint8_t> taken(map.points().slot_count(), 0);
  const size_t free_count = out->keyframes.size();
  for (size_t k = 0; k < free_count; ++k) {
    for (PointHandle p : map.keyframe(out->keyframes[k]).points) {
      if (p.is_null()) continue;
      const MapPoint* point = map.points().try_get(p);
      if (!point || taken[p.index()] || point->observations.size() < min_observations) continue;
      taken[p.index()] = 1;
      out->points.push_back(p);
      problem.points.push_back(point->position);
    }
  }
  size_t num_observations = 0;
  for (PointHandle p : out->points) num_observations += map.point(p).observations.size();
  problem.observations.reserve(num_observations);
  for (size_t j = 0; j < out->points.size(); ++j) {
    for (const Observation& o : map.point(out->points[j]).observations) {
      const uint32_t known = pose_of_slot[o.keyframe.index()];
      const uint32_t index = known != kNone ? known : add_pose(o.keyframe, true);  // outside: fixed
      const KeyFrame& kf = map.keyframe(o.keyframe);
      BundleAdjustmentObservation obs;
      obs.pose_index = index;
      obs.point_index = static_cast<uint32_t>(j);
      obs.uv = kf.uv[o.keypoint].cast<double>();
      obs.right_u = geometry.bf > 0 ? stereo.RightU(kf.uv[o.keypoint].x(), kf.right_u[o.keypoint], kf.depth[o.keypoint],
                                                    far_depth[index], geometry.pyramid.scale[kf.octave[o.keypoint]])
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
