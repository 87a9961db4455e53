#include "frontend/frame.h"

#include <algorithm>
#include <cmath>

namespace flatslam {

void FeatureGrid::Build(std::span<const Eigen::Vector2f> uv, int width, int height, float cell_px) {
  inv_cell_ = 1.0f / cell_px;
  cols_ = std::max(1, static_cast<int>(std::ceil(width * inv_cell_)));
  rows_ = std::max(1, static_cast<int>(std::ceil(height * inv_cell_)));
  const size_t cells = static_cast<size_t>(cols_) * rows_;
  std::vector<uint32_t> cell_of(uv.size());
  cell_start_.assign(cells + 1, 0);
  for (size_t i = 0; i < uv.size(); ++i) {
    const int c = std::clamp(static_cast<int>(uv[i].x() * inv_cell_), 0, cols_ - 1);
    const int r = std::clamp(static_cast<int>(uv[i].y() * inv_cell_), 0, rows_ - 1);
    cell_of[i] = static_cast<uint32_t>(r * cols_ + c);
    ++cell_start_[cell_of[i] + 1];
  }
  for (size_t c = 0; c < cells; ++c) cell_start_[c + 1] += cell_start_[c];
  indices_.resize(uv.size());
  std::vector<uint32_t> fill(cell_start_.begin(), cell_start_.end() - 1);
  for (size_t i = 0; i < uv.size(); ++i) indices_[fill[cell_of[i]]++] = static_cast<uint32_t>(i);
}

void FeatureGrid::Query(float u, float v, float r, std::span<const Eigen::Vector2f> uv,
                        std::vector<uint32_t>* out) const {
  if (cols_ == 0) return;
  const int c0 = std::max(0, static_cast<int>((u - r) * inv_cell_));
  const int c1 = std::min(cols_ - 1, static_cast<int>((u + r) * inv_cell_));
  const int r0 = std::max(0, static_cast<int>((v - r) * inv_cell_));
  const int r1 = std::min(rows_ - 1, static_cast<int>((v + r) * inv_cell_));
  for (int row = r0; row <= r1; ++row) {
    for (int col = c0; col <= c1; ++col) {
      const size_t cell = static_cast<size_t>(row) * cols_ + col;
      for (uint32_t k = cell_start_[cell]; k < cell_start_[cell + 1]; ++k) {
        const uint32_t i = indices_[k];
        if (std::abs(uv[i].x() - u) <= r && std::abs(uv[i].y() - v) <= r) out->push_back(i);
      }
    }
  }
}

void TrackedFrame::Prepare(int width, int height) {
  points.assign(keypoints.size(), PointHandle::null());
  outlier.assign(keypoints.size(), 0);
  grid.Build(keypoints.uv, width, height);
}

}  // namespace flatslam
