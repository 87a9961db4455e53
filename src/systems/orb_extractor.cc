#include "systems/orb_extractor.h"

#include <algorithm>
#include <cmath>
#include <numeric>

#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "core/error.h"

namespace flatslam {
namespace {

constexpr int kOrientationRadius = 15;  // intensity-centroid disc radius (level pixels)
constexpr int kPatternRadius = 13;      // BRIEF test points lie in this disc, so any rotation stays in it
constexpr int kDescriptorBits = 256;

// A FAST corner on one level, level coordinates.
struct Candidate {
  int16_t x, y;
  float response;
};

// A quadtree cell: region [x0,x1) x [y0,y1) and its candidates idx[begin, end).
struct Node {
  float x0, y0, x1, y1;
  uint32_t begin, end;
  [[nodiscard]] uint32_t count() const { return end - begin; }
  // Distinct integer positions can still be separated while the cell is wider than half a pixel.
  [[nodiscard]] bool splittable() const { return count() > 1 && (x1 - x0 > 0.5f || y1 - y0 > 0.5f); }
};

// splitmix64: a tiny, portable generator so the BRIEF pattern is the same on every platform.
struct SplitMix64 {
  uint64_t state;
  uint64_t Next() {
    uint64_t z = (state += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  double Uniform() { return (static_cast<double>(Next() >> 11) + 0.5) * 0x1.0p-53; }  // (0, 1)
  // Box-Muller, one value per call: std::normal_distribution differs between standard libraries.
  double Gaussian() { return std::sqrt(-2.0 * std::log(Uniform())) * std::cos(2.0 * M_PI * Uniform()); }
};

// 256 test pairs as in BRIEF's G II: both points drawn from an isotropic Gaussian with
// sigma = patch/5 (patch 31), kept inside the pattern disc; coincident or adjacent points and
// repeated pairs are redrawn, as their tests carry little information.
std::vector<std::array<int8_t, 4>> MakePattern(uint64_t seed) {
  SplitMix64 rng{seed};
  const double sigma = 31.0 / 5.0;
  auto draw_point = [&](int* x, int* y) {
    while (true) {
      *x = static_cast<int>(std::lround(sigma * rng.Gaussian()));
      *y = static_cast<int>(std::lround(sigma * rng.Gaussian()));
      if ((*x) * (*x) + (*y) * (*y) <= kPatternRadius * kPatternRadius) return;
    }
  };
  std::vector<std::array<int8_t, 4>> pattern;
  while (static_cast<int>(pattern.size()) < kDescriptorBits) {
    int x1, y1, x2, y2;
    draw_point(&x1, &y1);
    draw_point(&x2, &y2);
    if ((x1 - x2) * (x1 - x2) + (y1 - y2) * (y1 - y2) < 4) continue;
    const std::array<int8_t, 4> pair{static_cast<int8_t>(x1), static_cast<int8_t>(y1), static_cast<int8_t>(x2),
                                     static_cast<int8_t>(y2)};
    const std::array<int8_t, 4> swapped{pair[2], pair[3], pair[0], pair[1]};
    if (std::find(pattern.begin(), pattern.end(), pair) != pattern.end() ||
        std::find(pattern.begin(), pattern.end(), swapped) != pattern.end())
      continue;
    pattern.push_back(pair);
  }
  return pattern;
}

// Splits `total` into integer shares proportional to weights (cumulative rounding: exact sum).
std::vector<int> Apportion(int total, const std::vector<double>& weights) {
  const double sum = std::accumulate(weights.begin(), weights.end(), 0.0);
  std::vector<int> shares(weights.size(), 0);
  if (sum <= 0) return shares;
  double cumulative = 0;
  int given = 0;
  for (size_t i = 0; i < weights.size(); ++i) {
    cumulative += weights[i];
    const int upto = static_cast<int>(std::lround(total * cumulative / sum));
    shares[i] = upto - given;
    given = upto;
  }
  return shares;
}

// FAST corners in [m, cols-m) x [m, rows-m) of a level: one pass with the high threshold, then
// the low threshold in every grid cell that got nothing (textureless areas still get corners).
void DetectCorners(const cv::Mat& img, const OrbOptions& o, std::vector<Candidate>* out) {
  out->clear();
  const int m = o.edge_margin;
  const int width = img.cols - 2 * m, height = img.rows - 2 * m;
  if (width < 8 || height < 8) return;

  std::vector<cv::KeyPoint> corners;
  // FAST ignores a 3-pixel border of its input, so grow the region by 3.
  cv::FAST(img(cv::Rect(m - 3, m - 3, width + 6, height + 6)), corners, o.fast_threshold, true);
  out->reserve(corners.size() + 64);
  for (const cv::KeyPoint& k : corners) {
    out->push_back({static_cast<int16_t>(std::lround(k.pt.x) + m - 3),
                    static_cast<int16_t>(std::lround(k.pt.y) + m - 3), k.response});
  }

  const int cells_x = std::max(1, width / o.cell_size), cells_y = std::max(1, height / o.cell_size);
  const int cell_w = (width + cells_x - 1) / cells_x, cell_h = (height + cells_y - 1) / cells_y;
  std::vector<uint8_t> occupied(static_cast<size_t>(cells_x) * cells_y, 0);
  for (const Candidate& c : *out) {
    const int cx = std::min((c.x - m) / cell_w, cells_x - 1), cy = std::min((c.y - m) / cell_h, cells_y - 1);
    occupied[static_cast<size_t>(cy) * cells_x + cx] = 1;
  }
  if (o.min_fast_threshold >= o.fast_threshold) return;
  for (int cy = 0; cy < cells_y; ++cy) {
    for (int cx = 0; cx < cells_x; ++cx) {
      if (occupied[static_cast<size_t>(cy) * cells_x + cx]) continue;
      const int x0 = m + cx * cell_w, y0 = m + cy * cell_h;
      const int x1 = std::min(x0 + cell_w, m + width), y1 = std::min(y0 + cell_h, m + height);
      if (x1 - x0 < 1 || y1 - y0 < 1) continue;
      corners.clear();
      cv::FAST(img(cv::Rect(x0 - 3, y0 - 3, x1 - x0 + 6, y1 - y0 + 6)), corners, o.min_fast_threshold, true);
      for (const cv::KeyPoint& k : corners) {
        out->push_back({static_cast<int16_t>(std::lround(k.pt.x) + x0 - 3),
                        static_cast<int16_t>(std::lround(k.pt.y) + y0 - 3), k.response});
      }
    }
  }
}

// Splits a node into its non-empty quarters, partitioning idx in place.
void SplitNode(const Node& n, const std::vector<Candidate>& cands, std::vector<uint32_t>* idx,
               std::vector<Node>* children) {
  const float xm = 0.5f * (n.x0 + n.x1), ym = 0.5f * (n.y0 + n.y1);
  auto first = idx->begin() + n.begin, last = idx->begin() + n.end;
  auto mid_y = std::partition(first, last, [&](uint32_t i) { return cands[i].y < ym; });
  auto mid_top = std::partition(first, mid_y, [&](uint32_t i) { return cands[i].x < xm; });
  auto mid_bottom = std::partition(mid_y, last, [&](uint32_t i) { return cands[i].x < xm; });
  const auto at = [&](auto it) { return static_cast<uint32_t>(it - idx->begin()); };
  const Node quarters[4] = {{n.x0, n.y0, xm, ym, n.begin, at(mid_top)},
                            {xm, n.y0, n.x1, ym, at(mid_top), at(mid_y)},
                            {n.x0, ym, xm, n.y1, at(mid_y), at(mid_bottom)},
                            {xm, ym, n.x1, n.y1, at(mid_bottom), n.end}};
  for (const Node& q : quarters) {
    if (q.count() > 0) children->push_back(q);
  }
}

// Keeps at most `budget` candidates spread over the region: quarters cells (largest first once
// close to the budget) until there are `budget` non-empty cells, then keeps each cell's strongest.
// Output sorted by (y, x).
void Distribute(const std::vector<Candidate>& cands, float x0, float y0, float x1, float y1, int budget,
                std::vector<Candidate>* out) {
  out->clear();
  if (budget <= 0 || cands.empty()) return;
  const auto by_position = [](const Candidate& a, const Candidate& b) {
    return a.y != b.y ? a.y < b.y : a.x < b.x;
  };
  if (static_cast<int>(cands.size()) <= budget) {
    *out = cands;
    std::sort(out->begin(), out->end(), by_position);
    return;
  }
  std::vector<uint32_t> idx(cands.size());
  std::iota(idx.begin(), idx.end(), 0u);

  // Start from roughly square cells: a wide image begins with several columns, a tall one rows.
  const float w = x1 - x0, h = y1 - y0;
  const int nx = std::max(1, static_cast<int>(std::lround(w / h)));
  const int ny = std::max(1, static_cast<int>(std::lround(h / w)));
  std::vector<Node> nodes, next;
  {
    auto row_begin = idx.begin();
    for (int j = 0; j < ny; ++j) {
      const float ya = y0 + h * j / ny, yb = j + 1 == ny ? y1 : y0 + h * (j + 1) / ny;
      auto row_end = j + 1 == ny ? idx.end() : std::partition(row_begin, idx.end(), [&](uint32_t i) { return cands[i].y < yb; });
      auto col_begin = row_begin;
      for (int i = 0; i < nx; ++i) {
        const float xa = x0 + w * i / nx, xb = i + 1 == nx ? x1 : x0 + w * (i + 1) / nx;
        auto col_end = i + 1 == nx ? row_end : std::partition(col_begin, row_end, [&](uint32_t k) { return cands[k].x < xb; });
        const Node n{xa, ya, xb, yb, static_cast<uint32_t>(col_begin - idx.begin()),
                     static_cast<uint32_t>(col_end - idx.begin())};
        if (n.count() > 0) nodes.push_back(n);
        col_begin = col_end;
      }
      row_begin = row_end;
    }
  }

  std::vector<uint32_t> order;
  while (static_cast<int>(nodes.size()) < budget) {
    size_t expandable = 0;
    for (const Node& n : nodes) expandable += n.splittable();
    if (expandable == 0) break;
    next.clear();
    if (nodes.size() + 3 * expandable <= static_cast<size_t>(budget)) {
      // A full round cannot overshoot: split every cell.
      for (const Node& n : nodes) {
        if (n.splittable()) {
          SplitNode(n, cands, &idx, &next);
        } else {
          next.push_back(n);
        }
      }
    } else {
      // Last round: split the most crowded cells first and stop at the budget.
      order.clear();
      for (uint32_t i = 0; i < nodes.size(); ++i) {
        if (nodes[i].splittable()) order.push_back(i);
      }
      std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) {
        return nodes[a].count() != nodes[b].count() ? nodes[a].count() > nodes[b].count() : a < b;
      });
      std::vector<uint8_t> split(nodes.size(), 0);
      size_t count = nodes.size();
      std::vector<Node> children;
      for (uint32_t i : order) {
        const size_t before = children.size();
        SplitNode(nodes[i], cands, &idx, &children);
        split[i] = 1;
        count += children.size() - before - 1;
        if (count >= static_cast<size_t>(budget)) break;
      }
      for (uint32_t i = 0; i < nodes.size(); ++i) {
        if (!split[i]) next.push_back(nodes[i]);
      }
      next.insert(next.end(), children.begin(), children.end());
    }
    nodes.swap(next);
  }

  out->reserve(nodes.size());
  for (const Node& n : nodes) {
    uint32_t best = idx[n.begin];
    for (uint32_t k = n.begin + 1; k < n.end; ++k) {
      const uint32_t c = idx[k];
      if (cands[c].response > cands[best].response ||
          (cands[c].response == cands[best].response && by_position(cands[c], cands[best])))
        best = c;
    }
    out->push_back(cands[best]);
  }
  if (static_cast<int>(out->size()) > budget) {
    std::nth_element(out->begin(), out->begin() + budget, out->end(), [&](const Candidate& a, const Candidate& b) {
      return a.response != b.response ? a.response > b.response : by_position(a, b);
    });
    out->resize(budget);
  }
  std::sort(out->begin(), out->end(), by_position);
}

// Direction of the intensity centroid of the disc around (x, y): atan2(m01, m10), radians.
float CentroidAngle(const cv::Mat& img, int x, int y, const std::vector<int>& half_width) {
  const uint8_t* center = img.ptr<uint8_t>(y) + x;
  const ptrdiff_t step = static_cast<ptrdiff_t>(img.step1());
  int m10 = 0, m01 = 0;
  for (int u = -kOrientationRadius; u <= kOrientationRadius; ++u) m10 += u * center[u];
  for (int v = 1; v <= kOrientationRadius; ++v) {
    const uint8_t* below = center + v * step;
    const uint8_t* above = center - v * step;
    const int hw = half_width[v];
    int diff = 0;
    for (int u = -hw; u <= hw; ++u) {
      const int b = below[u], a = above[u];
      m10 += u * (b + a);
      diff += b - a;
    }
    m01 += v * diff;
  }
  return std::atan2(static_cast<float>(m01), static_cast<float>(m10));
}

// Steered BRIEF on the blurred level: the pattern rotated by `angle`, points rounded to pixels.
Descriptor SteeredBrief(const cv::Mat& blurred, int x, int y, float angle, const float* px1, const float* py1,
                        const float* px2, const float* py2) {
  const uint8_t* center = blurred.ptr<uint8_t>(y) + x;
  const int step = static_cast<int>(blurred.step1());
  const float c = std::cos(angle), s = std::sin(angle);
  alignas(64) int off1[kDescriptorBits], off2[kDescriptorBits];
  // Rounds to nearest by truncating a value shifted positive (vectorises without SSE4.1).
  const auto round = [](float v) { return static_cast<int>(v + 64.5f) - 64; };
  for (int k = 0; k < kDescriptorBits; ++k) {
    off1[k] = round(px1[k] * s + py1[k] * c) * step + round(px1[k] * c - py1[k] * s);
    off2[k] = round(px2[k] * s + py2[k] * c) * step + round(px2[k] * c - py2[k] * s);
  }
  Descriptor d{};
  for (int word = 0; word < 4; ++word) {
    uint64_t bits = 0;
    for (int b = 0; b < 64; ++b) {
      const int k = word * 64 + b;
      bits |= static_cast<uint64_t>(center[off1[k]] < center[off2[k]]) << b;
    }
    d[word] = bits;
  }
  return d;
}

// What one level produces.
struct LevelResult {
  std::vector<Candidate> corners;  // all FAST candidates, then the kept ones
  std::vector<float> angle;
  std::vector<Descriptor> descriptor;
};

}  // namespace

bool OrbOptions::Check() const {
  return features >= 1 && levels >= 1 && levels <= 32 && (scale_factor > 1.f || levels == 1) &&
         fast_threshold >= 1 && min_fast_threshold >= 1 && min_fast_threshold <= fast_threshold &&
         cell_size >= 8 && edge_margin >= kOrientationRadius + 1 && edge_margin <= 1000 && blur_sigma >= 0 &&
         blur_kernel >= 1 && blur_kernel % 2 == 1 && blur_kernel <= 31;
}

Eigen::Vector2f ImagePyramid::ToLevel(const Eigen::Vector2f& uv0, int level) const {
  const float sx = static_cast<float>(levels[0].cols) / levels[level].cols;
  const float sy = static_cast<float>(levels[0].rows) / levels[level].rows;
  return {(uv0.x() + 0.5f) / sx - 0.5f, (uv0.y() + 0.5f) / sy - 0.5f};
}

Eigen::Vector2f ImagePyramid::FromLevel(const Eigen::Vector2f& uv, int level) const {
  const float sx = static_cast<float>(levels[0].cols) / levels[level].cols;
  const float sy = static_cast<float>(levels[0].rows) / levels[level].rows;
  return {(uv.x() + 0.5f) * sx - 0.5f, (uv.y() + 0.5f) * sy - 0.5f};
}

OrbExtractor::OrbExtractor(const OrbOptions& options)
    : options_(options), scales_(ScalePyramid::Make(options.levels, options.scale_factor)) {
  FLATSLAM_CHECK(options.Check(), "OrbExtractor: invalid OrbOptions (features ", options.features, ", levels ",
                 options.levels, ", scale_factor ", options.scale_factor, ", thresholds ", options.fast_threshold,
                 "/", options.min_fast_threshold, ", edge_margin ", options.edge_margin, ")");
  std::vector<double> weights;
  for (int i = 0; i < options.levels; ++i) {
    weights.push_back(options.budget_by_area ? scales_.inv_sigma2[i] : scales_.inv_scale[i]);
  }
  level_budget_ = Apportion(options.features, weights);
  pattern_ = MakePattern(options.pattern_seed);
  // Disc u^2 + v^2 <= (r + 1/2)^2: symmetric under 90-degree rotations and mirroring.
  for (int v = 0; v <= kOrientationRadius; ++v) {
    const double r = kOrientationRadius + 0.5;
    circle_half_width_.push_back(static_cast<int>(std::floor(std::sqrt(r * r - v * v))));
  }
}

void OrbExtractor::BuildPyramid(const cv::Mat& gray, ImagePyramid* pyramid) const {
  FLATSLAM_CHECK(!gray.empty(), "OrbExtractor: empty image");
  FLATSLAM_CHECK(gray.type() == CV_8UC1, "OrbExtractor: image must be CV_8UC1 (gray), got type ", gray.type());
  FLATSLAM_CHECK(pyramid != nullptr, "OrbExtractor: null pyramid");
  pyramid->levels.resize(options_.levels);
  pyramid->levels[0] = gray;
  for (int i = 1; i < options_.levels; ++i) {
    const cv::Size size(std::max(1, static_cast<int>(std::lround(gray.cols * scales_.inv_scale[i]))),
                        std::max(1, static_cast<int>(std::lround(gray.rows * scales_.inv_scale[i]))));
    cv::resize(pyramid->levels[i - 1], pyramid->levels[i], size, 0, 0, cv::INTER_LINEAR);
  }
}

void OrbExtractor::Extract(const cv::Mat& gray, Keypoints* out) const {
  ImagePyramid pyramid;
  Extract(gray, out, &pyramid);
}

void OrbExtractor::Extract(const cv::Mat& gray, Keypoints* out, ImagePyramid* pyramid) const {
  FLATSLAM_CHECK(out != nullptr, "OrbExtractor: null output");
  BuildPyramid(gray, pyramid);
  const int levels = options_.levels;
  std::vector<LevelResult> results(levels);

  // 1. Candidates per level.
  tbb::parallel_for(tbb::blocked_range<int>(0, levels, 1), [&](const tbb::blocked_range<int>& range) {
    for (int l = range.begin(); l != range.end(); ++l) DetectCorners(pyramid->levels[l], options_, &results[l].corners);
  });

  // 2. Budgets: each level's share, then the shortfall of sparse levels handed to the others.
  std::vector<int> take(levels);
  for (int l = 0; l < levels; ++l) take[l] = std::min<int>(level_budget_[l], results[l].corners.size());
  for (int round = 0; round < levels; ++round) {
    const int deficit = options_.features - std::accumulate(take.begin(), take.end(), 0);
    if (deficit <= 0) break;
    std::vector<double> weights(levels, 0.0);
    for (int l = 0; l < levels; ++l) {
      if (static_cast<int>(results[l].corners.size()) > take[l]) weights[l] = level_budget_[l] + 1.0;
    }
    const std::vector<int> extra = Apportion(deficit, weights);
    bool changed = false;
    for (int l = 0; l < levels; ++l) {
      const int add = std::min<int>(extra[l], static_cast<int>(results[l].corners.size()) - take[l]);
      take[l] += add;
      changed |= add > 0;
    }
    if (!changed) break;
  }

  // 3. Spread, orientation and descriptors per level.
  std::array<float, kDescriptorBits> px1, py1, px2, py2;
  for (int k = 0; k < kDescriptorBits; ++k) {
    px1[k] = pattern_[k][0];
    py1[k] = pattern_[k][1];
    px2[k] = pattern_[k][2];
    py2[k] = pattern_[k][3];
  }
  const int m = options_.edge_margin;
  tbb::parallel_for(tbb::blocked_range<int>(0, levels, 1), [&](const tbb::blocked_range<int>& range) {
    std::vector<Candidate> kept;
    cv::Mat blurred;
    for (int l = range.begin(); l != range.end(); ++l) {
      LevelResult& r = results[l];
      const cv::Mat& img = pyramid->levels[l];
      Distribute(r.corners, static_cast<float>(m), static_cast<float>(m), static_cast<float>(img.cols - m),
                 static_cast<float>(img.rows - m), take[l], &kept);
      r.corners.swap(kept);
      r.angle.resize(r.corners.size());
      r.descriptor.resize(r.corners.size());
      if (r.corners.empty()) continue;
      for (size_t i = 0; i < r.corners.size(); ++i) {
        r.angle[i] = CentroidAngle(img, r.corners[i].x, r.corners[i].y, circle_half_width_);
      }
      if (options_.blur_sigma > 0) {
        cv::GaussianBlur(img, blurred, cv::Size(options_.blur_kernel, options_.blur_kernel), options_.blur_sigma,
                         options_.blur_sigma, cv::BORDER_REFLECT_101);
      } else {
        blurred = img;
      }
      for (size_t i = 0; i < r.corners.size(); ++i) {
        r.descriptor[i] = SteeredBrief(blurred, r.corners[i].x, r.corners[i].y, r.angle[i], px1.data(), py1.data(),
                                       px2.data(), py2.data());
      }
    }
  });

  // 4. Concatenate in level order, coordinates mapped to level 0.
  size_t total = 0;
  for (const LevelResult& r : results) total += r.corners.size();
  out->resize(0);
  out->resize(total);
  size_t k = 0;
  for (int l = 0; l < levels; ++l) {
    const LevelResult& r = results[l];
    for (size_t i = 0; i < r.corners.size(); ++i, ++k) {
      out->uv[k] = pyramid->FromLevel(Eigen::Vector2f(r.corners[i].x, r.corners[i].y), l);
      out->angle[k] = r.angle[i];
      out->octave[k] = static_cast<uint8_t>(l);
      out->response[k] = r.corners[i].response;
      out->descriptor[k] = r.descriptor[i];
    }
  }
}

}  // namespace flatslam
