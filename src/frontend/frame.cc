#include "frontend/frame.h"

#include <algorithm>
#include <cmath>

namespace flatslam {

void FeatureGrid::Build(std::span<const Eigen::Vector2f> uv, int width, int height, float cell_px) {
  Layout(uv, width, height, {}, cell_px);
}

void FeatureGrid::Layout(std::span<const Eigen::Vector2f> uv, int width, int height, std::span<const uint8_t> keep,
                         float cell_px) {
  inv_cell_ = 1.0f / cell_px;
  cols_ = std::max(1, static_cast<int>(std::ceil(width * inv_cell_)));
  rows_ = std::max(1, static_cast<int>(std::ceil(height * inv_cell_)));
  const size_t cells = static_cast<size_t>(cols_) * rows_;
  constexpr uint32_t kSkipped = ~uint32_t{0};
  std::vector<uint32_t> cell_of(uv.size(), kSkipped);
  cell_start_.assign(cells + 1, 0);
  size_t kept = 0;
  for (size_t i = 0; i < uv.size(); ++i) {
    if (!keep.empty() && !keep[i]) continue;
    const int c = std::clamp(static_cast<int>(uv[i].x() * inv_cell_), 0, cols_ - 1);
    const int r = std::clamp(static_cast<int>(uv[i].y() * inv_cell_), 0, rows_ - 1);
    cell_of[i] = static_cast<uint32_t>(r * cols_ + c);
    ++cell_start_[cell_of[i] + 1];
    ++kept;
  }
  for (size_t c = 0; c < cells; ++c) cell_start_[c + 1] += cell_start_[c];
  indices_.resize(kept);
  uv_.resize(kept);
  std::vector<uint32_t> fill(cell_start_.begin(), cell_start_.end() - 1);
  for (size_t i = 0; i < uv.size(); ++i) {
    if (cell_of[i] == kSkipped) continue;
    const uint32_t k = fill[cell_of[i]]++;
    indices_[k] = static_cast<uint32_t>(i);
    uv_[k] = uv[i];
  }
}

void FeatureGrid::Query(float u, float v, float r, std::vector<uint32_t>* out) const {
  if (cols_ == 0) return;
  const int c0 = std::max(0, static_cast<int>((u - r) * inv_cell_));
  const int c1 = std::min(cols_ - 1, static_cast<int>((u + r) * inv_cell_));
  const int r0 = std::max(0, static_cast<int>((v - r) * inv_cell_));
  const int r1 = std::min(rows_ - 1, static_cast<int>((v + r) * inv_cell_));
  // Cells c0..c1 of a row are one run of the grid order. Every index of the runs is written and
  // the write position advances only past those inside the square: no branch on each keypoint's
  // position, whose outcome a dense cell makes unpredictable (same indices, same order).
  size_t scanned = 0;
  for (int row = r0; row <= r1; ++row) {
    const size_t first = static_cast<size_t>(row) * cols_;
    scanned += cell_start_[first + c1 + 1] - cell_start_[first + c0];
  }
  if (scanned == 0) return;
  const size_t start = out->size();
  out->resize(start + scanned);
  uint32_t* write = out->data() + start;
  for (int row = r0; row <= r1; ++row) {
    const size_t first = static_cast<size_t>(row) * cols_;
    for (uint32_t k = cell_start_[first + c0]; k < cell_start_[first + c1 + 1]; ++k) {
      *write = indices_[k];
      write += static_cast<size_t>((std::abs(uv_[k].x() - u) <= r) & (std::abs(uv_[k].y() - v) <= r));
    }
  }
  out->resize(static_cast<size_t>(write - out->data()));
}

void TrackedFrame::Prepare(int width, int height) {
  points.assign(keypoints.size(), PointHandle::null());
  outlier.assign(keypoints.size(), 0);
  grid.Build(keypoints.uv, width, height);
}

}  // namespace flatslam
