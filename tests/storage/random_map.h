// Random maps built through the Map API (keyframes with full keypoint columns, points with
// observations, covisibility, spanning tree, loop edges), for snapshot tests and benchmarks.
// Concurrency: plain functions; each call owns its generator.
#pragma once

#include <algorithm>
#include <cstdint>
#include <random>
#include <vector>

#include "ecs/map.h"
#include "storage/keyframe_message.h"

namespace flatslam::testing {

struct RandomMapOptions {
  size_t keyframes = 20;
  size_t keypoints = 300;  // per keyframe
  size_t points = 1000;
  size_t observations_per_point = 4;  // consecutive keyframes see each point
  size_t loop_edges = 2;
  uint32_t agents = 2;
  bool erase_some = true;  // erase and re-add a few entities: generations and reordered dense arrays
  uint64_t seed = 7;
};

// A stereo camera for keyframe messages of random maps.
inline AgentCamera TestAgentCamera() {
  AgentCamera camera;
  camera.calibration.sensor = Sensor::kStereo;
  camera.calibration.camera = PinholeCamera{480, 480, 319.5, 239.5, 640, 480};
  camera.calibration.baseline_m = 0.12;
  camera.calibration.frame_rate_hz = 20;
  camera.scales = MapScales{1.2f, 8};
  return camera;
}

inline Map RandomMap(const RandomMapOptions& o) {
  std::mt19937_64 rng(o.seed);
  std::uniform_real_distribution<float> pixel(0.0f, 640.0f), unit(-1.0f, 1.0f);
  std::uniform_real_distribution<double> coord(-20.0, 20.0);
  Map map;
  map.keyframes().reserve(o.keyframes);
  map.points().reserve(o.points);
  std::vector<KeyFrameHandle> kfs;
  for (size_t i = 0; i < o.keyframes; ++i) {
    KeyFrame kf;
    kf.frame_index = i * 3;
    kf.t_ns = static_cast<int64_t>(i) * 100'000'000 + 12345;
    kf.agent = static_cast<uint32_t>(i % o.agents);
    kf.T_cam_world = Eigen::Translation3d(coord(rng), coord(rng), coord(rng)) *
                     Eigen::Quaterniond(1.0, unit(rng), unit(rng), unit(rng)).normalized();
    kf.resize(o.keypoints);
    for (size_t k = 0; k < o.keypoints; ++k) {
      kf.uv.mutable_data()[k] = {pixel(rng), pixel(rng)};
      kf.right_u.mutable_data()[k] = (k % 3 == 0) ? -1.0f : pixel(rng);
      kf.depth.mutable_data()[k] = (k % 3 == 0) ? -1.0f : 1.0f + 10.0f * std::abs(unit(rng));
      kf.angle.mutable_data()[k] = 3.14f * unit(rng);
      kf.octave.mutable_data()[k] = static_cast<uint8_t>(rng() % 8);
      kf.descriptor.mutable_data()[k] = {rng(), rng(), rng(), rng()};
    }
    kfs.push_back(map.AddKeyFrame(std::move(kf)));
  }
  // Each point is seen by a run of consecutive keyframes, at the next free keypoint of each.
  std::vector<uint32_t> next_free(o.keyframes, 0);
  const size_t span = std::min(o.observations_per_point, o.keyframes);
  for (size_t i = 0; i < o.points; ++i) {
    const size_t first = (i * 7919) % (o.keyframes - span + 1);
    const PointHandle p = map.AddPoint({coord(rng), coord(rng), coord(rng)}, kfs[first]);
    MapPoint& point = map.point(p);
    point.descriptor = {rng(), rng(), rng(), rng()};
    point.normal = Eigen::Vector3d(unit(rng), unit(rng), 1.0).normalized();
    point.min_distance = 0.5f + std::abs(unit(rng));
    point.max_distance = point.min_distance * 8;
    point.visible = 3 + static_cast<uint32_t>(rng() % 20);
    point.found = 1 + static_cast<uint32_t>(rng() % 3);
    point.observations.reserve(span);
    for (size_t j = first; j < first + span; ++j) {
      if (next_free[j] >= o.keypoints) continue;
      map.AddObservation(p, kfs[j], next_free[j]++);
    }
  }
  for (KeyFrameHandle kf : kfs) map.UpdateCovisibility(kf, 1);
  for (size_t i = 0; i < o.loop_edges && o.keyframes > 2; ++i) map.AddLoopEdge(kfs[i], kfs[o.keyframes - 1 - i]);
  if (o.erase_some && o.keyframes > 6) {
    map.EraseKeyFrame(kfs[o.keyframes / 2]);
    const auto handles = map.points().handles();
    std::vector<PointHandle> doomed(handles.begin(), handles.begin() + std::min<size_t>(3, handles.size()));
    for (PointHandle p : doomed) map.ErasePoint(p);
    const PointHandle reborn = map.AddPoint({1, 2, 3}, kfs[1]);
    if (next_free[1] < o.keypoints) map.AddObservation(reborn, kfs[1], next_free[1]++);
  }
  return map;
}

}  // namespace flatslam::testing
