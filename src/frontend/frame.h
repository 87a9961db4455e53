// A frame being tracked: its keypoints, a grid for radius queries, its map-point matches and pose.
// Concurrency: owned by one pipeline item; the extract stage writes it, the track stage reads it.
#pragma once

#include <cstdint>
#include <span>
#include <vector>

#include <Eigen/Geometry>

#include "ecs/bow.h"
#include "ecs/map.h"
#include "frontend/features.h"

namespace flatslam {

// Keypoint indices bucketed into square cells (compressed rows) for radius queries.
class FeatureGrid {
 public:
  void Build(std::span<const Eigen::Vector2f> uv, int width, int height, float cell_px = 24.0f);
  // The same over the keypoints i with keep(i) only (queries return their indices into uv).
  template <typename Keep>
  void BuildWhere(std::span<const Eigen::Vector2f> uv, int width, int height, Keep keep, float cell_px = 24.0f);
  // Appends to out the keypoints (indices into the uv it was built from) within the square of
  // half-size r around (u, v), cell by cell, each cell's in keypoint order.
  void Query(float u, float v, float r, std::vector<uint32_t>* out) const;

 private:
  int cols_ = 0, rows_ = 0;
  float inv_cell_ = 1;
  std::vector<uint32_t> cell_start_;  // cols_*rows_ + 1 offsets into indices_
  std::vector<uint32_t> indices_;
  std::vector<Eigen::Vector2f> uv_;  // uv[indices_[k]], read in order by queries

  // Lays out the keypoints i with keep[i] (all of them when keep is empty), each cell's in index
  // order.
  void Layout(std::span<const Eigen::Vector2f> uv, int width, int height, std::span<const uint8_t> keep,
              float cell_px);
};

template <typename Keep>
void FeatureGrid::BuildWhere(std::span<const Eigen::Vector2f> uv, int width, int height, Keep keep, float cell_px) {
  std::vector<uint8_t> mask(uv.size());
  for (size_t i = 0; i < uv.size(); ++i) mask[i] = keep(i) ? 1 : 0;
  Layout(uv, width, height, mask, cell_px);
}

struct TrackedFrame {
  size_t index = 0;
  int64_t t_ns = 0;
  Keypoints keypoints;
  FeatureGrid grid;
  std::vector<PointHandle> points;  // matched map point per keypoint (null = none)
  std::vector<uint8_t> outlier;     // set by pose optimization
  Eigen::Isometry3d T_cam_world = Eigen::Isometry3d::Identity();
  bool has_pose = false;
  // Bag of words, filled when place recognition needs it (relocalization, new keyframes).
  BowVector bow;
  FeatureVector bow_features;

  // Sizes points/outlier to the keypoints and builds the grid.
  void Prepare(int width, int height);
  [[nodiscard]] size_t size() const { return keypoints.size(); }
};

}  // namespace flatslam
