#include "systems/orb_extractor.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <numeric>
#include <unordered_set>

#include <opencv2/imgproc.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include "core/error.h"

// Vector-extension helpers are always inlined; their by-value ABI never crosses a call.
#pragma GCC diagnostic ignored "-Wpsabi"

namespace flatslam {
namespace {

constexpr int kOrientationRadius = 15;  // intensity-centroid disc radius (level pixels)
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

// ---- FAST scores -------------------------------------------------------------------------
// A pixel's score is the largest, over the 16 arcs of 9 contiguous pixels of the radius-3
// circle, of the smallest difference to the centre along the arc, on the brighter or the darker
// side. So the pixel is a FAST-9 corner at threshold t (all 9 brighter than centre + t or all
// darker than centre - t) exactly when score > t: one pass serves every threshold.

// The radius-3 Bresenham circle, clockwise from the top.
constexpr int kCircle[16][2] = {{0, -3}, {1, -3}, {2, -2}, {3, -1}, {3, 0},  {3, 1},  {2, 2},   {1, 3},
                                {0, 3},  {-1, 3}, {-2, 2}, {-3, 1}, {-3, 0}, {-3, -1}, {-2, -2}, {-1, -3}};

// 32 pixels per vector (GCC/Clang vector extension: two SSE2 registers, or one AVX2 register).
using Bytes32 = uint8_t __attribute__((vector_size(32)));

[[gnu::always_inline]] inline Bytes32 Load32(const uint8_t* p) {
  Bytes32 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
[[gnu::always_inline]] inline Bytes32 Min32(Bytes32 a, Bytes32 b) { return a < b ? a : b; }
[[gnu::always_inline]] inline Bytes32 Max32(Bytes32 a, Bytes32 b) { return a > b ? a : b; }

// max over k of min(d[k], ..., d[k+8]) (indices mod 16), by doubling windows: 2, 4, 8, then 9.
[[gnu::always_inline]] inline Bytes32 BestArc(const Bytes32 (&d)[16]) {
  Bytes32 m2[16], m4[16];
  for (int k = 0; k < 16; ++k) m2[k] = Min32(d[k], d[(k + 1) & 15]);
  for (int k = 0; k < 16; ++k) m4[k] = Min32(m2[k], m2[(k + 2) & 15]);
  Bytes32 best = {};
  for (int k = 0; k < 16; ++k) best = Max32(best, Min32(Min32(m4[k], m4[(k + 4) & 15]), d[(k + 8) & 15]));
  return best;
}

// Scalar reference of the same score (narrow images and tests).
uint8_t FastScoreAt(const uint8_t* p, const ptrdiff_t* offsets) {
  const int c = p[0];
  int best = 0;
  for (int side = 0; side < 2; ++side) {
    int d[16];
    for (int k = 0; k < 16; ++k) d[k] = std::max(0, side == 0 ? p[offsets[k]] - c : c - p[offsets[k]]);
    for (int k = 0; k < 16; ++k) {
      int m = 255;
      for (int j = 0; j < 9; ++j) m = std::min(m, d[(k + j) & 15]);
      best = std::max(best, m);
    }
  }
  return static_cast<uint8_t>(best);
}

// Scores of the pixels [x0, x1) x [y0, y1) of img (all at least 3 px inside) into out, whose
// row stride is out_step and whose first element is pixel (x0, y0).
[[gnu::always_inline]] inline void FastScoresBody(const cv::Mat& img, int x0, int y0, int x1, int y1, uint8_t* out,
                                                  size_t out_step) {
  const ptrdiff_t step = static_cast<ptrdiff_t>(img.step1());
  ptrdiff_t offsets[16];
  for (int k = 0; k < 16; ++k) offsets[k] = kCircle[k][1] * step + kCircle[k][0];
  const int count = x1 - x0;
  for (int y = y0; y < y1; ++y) {
    const uint8_t* row = img.ptr<uint8_t>(y) + x0;
    uint8_t* dst = out + (y - y0) * out_step;
    if (count < 32) {
      for (int x = 0; x < count; ++x) dst[x] = FastScoreAt(row + x, offsets);
      continue;
    }
    for (int x = 0;; x += 32) {
      if (x + 32 > count) x = count - 32;  // last block overlaps the previous one
      const uint8_t* p = row + x;
      const Bytes32 c = Load32(p);
      Bytes32 d[16];
      for (int k = 0; k < 16; ++k) {
        const Bytes32 v = Load32(p + offsets[k]);
        d[k] = v - Min32(v, c);  // saturated v - c
      }
      Bytes32 score = BestArc(d);
      for (int k = 0; k < 16; ++k) {
        const Bytes32 v = Load32(p + offsets[k]);
        d[k] = c - Min32(v, c);  // saturated c - v
      }
      score = Max32(score, BestArc(d));
      std::memcpy(dst + x, &score, sizeof(score));
      if (x + 32 >= count) break;
    }
  }
}

// Separable blur with integer taps summing to 256 and reflect-101 borders; loops over columns
// vectorise. row is scratch of cols + taps - 1 bytes, acc of cols values.
[[gnu::always_inline]] inline void BlurBody(const cv::Mat& src, const std::vector<uint16_t>& taps, cv::Mat* dst,
                                            std::vector<uint8_t>* row, std::vector<uint16_t>* acc) {
  const int cols = src.cols, rows = src.rows, size = static_cast<int>(taps.size()), r = size / 2;
  dst->create(rows, cols, CV_8UC1);
  row->resize(cols + 2 * r);
  acc->resize(cols);
  uint16_t* a = acc->data();
  uint8_t* padded = row->data();
  const auto reflect = [](int i, int n) {
    while (i < 0 || i >= n) i = i < 0 ? -i : 2 * (n - 1) - i;
    return i;
  };
  for (int y = 0; y < rows; ++y) {
    // Vertical pass into the middle of the padded row.
    std::fill(a, a + cols, uint16_t{128});
    for (int k = 0; k < size; ++k) {
      const uint8_t* s = src.ptr<uint8_t>(reflect(y + k - r, rows));
      const uint16_t w = taps[k];
      for (int x = 0; x < cols; ++x) a[x] = static_cast<uint16_t>(a[x] + w * s[x]);
    }
    for (int x = 0; x < cols; ++x) padded[x + r] = static_cast<uint8_t>(a[x] >> 8);
    for (int j = 1; j <= r; ++j) {
      padded[r - j] = padded[r + reflect(j, cols)];
      padded[r + cols - 1 + j] = padded[r + reflect(cols - 1 - j, cols)];
    }
    // Horizontal pass.
    std::fill(a, a + cols, uint16_t{128});
    for (int k = 0; k < size; ++k) {
      const uint8_t* s = padded + k;
      const uint16_t w = taps[k];
      for (int x = 0; x < cols; ++x) a[x] = static_cast<uint16_t>(a[x] + w * s[x]);
    }
    uint8_t* d = dst->ptr<uint8_t>(y);
    for (int x = 0; x < cols; ++x) d[x] = static_cast<uint8_t>(a[x] >> 8);
  }
}

// Runtime dispatch: the same bodies compiled for AVX2 where the CPU has it (identical results).
#if defined(__x86_64__) || defined(__i386__)
__attribute__((target("avx2"))) void FastScoresAvx2(const cv::Mat& img, int x0, int y0, int x1, int y1, uint8_t* out,
                                                   size_t out_step) {
  FastScoresBody(img, x0, y0, x1, y1, out, out_step);
}
__attribute__((target("avx2"))) void BlurAvx2(const cv::Mat& src, const std::vector<uint16_t>& taps, cv::Mat* dst,
                                             std::vector<uint8_t>* row, std::vector<uint16_t>* acc) {
  BlurBody(src, taps, dst, row, acc);
}
bool HasAvx2() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx2");
}
#endif

void ComputeFastScores(const cv::Mat& img, int x0, int y0, int x1, int y1, uint8_t* out, size_t out_step) {
#if defined(__x86_64__) || defined(__i386__)
  if (HasAvx2()) return FastScoresAvx2(img, x0, y0, x1, y1, out, out_step);
#endif
  FastScoresBody(img, x0, y0, x1, y1, out, out_step);
}

void Blur(const cv::Mat& src, const std::vector<uint16_t>& taps, cv::Mat* dst, std::vector<uint8_t>* row,
          std::vector<uint16_t>* acc) {
#if defined(__x86_64__) || defined(__i386__)
  if (HasAvx2()) return BlurAvx2(src, taps, dst, row, acc);
#endif
  BlurBody(src, taps, dst, row, acc);
}

// Integer Gaussian taps summing to exactly 256 (largest remainders go to the centre).
std::vector<uint16_t> GaussianTaps(int size, double sigma) {
  if (sigma <= 0 || size <= 1) return {256};
  std::vector<double> g(size);
  const int r = size / 2;
  double sum = 0;
  for (int i = 0; i < size; ++i) sum += g[i] = std::exp(-0.5 * (i - r) * (i - r) / (sigma * sigma));
  std::vector<uint16_t> taps(size);
  int total = 0;
  for (int i = 0; i < size; ++i) total += taps[i] = static_cast<uint16_t>(std::lround(256 * g[i] / sum));
  taps[r] = static_cast<uint16_t>(taps[r] + 256 - total);
  return taps;
}

// Per-level scratch, owned by one work item.
struct Scratch {
  std::vector<uint8_t> scores;
  std::vector<uint8_t> cell_has_strong;
  std::vector<Candidate> kept;
  cv::Mat blurred;
  std::vector<uint8_t> blur_row;
  std::vector<uint16_t> blur_acc;
};

// FAST corners in [m, cols-m) x [m, rows-m) of a level, after 3x3 non-maximum suppression
// (ties go to the first in raster order): those above the high threshold, plus those above the
// low one in grid cells without any (textureless areas still get corners). Raster order.
void DetectCorners(const cv::Mat& img, const OrbOptions& o, Scratch* scratch, std::vector<Candidate>* out) {
  out->clear();
  const int m = o.edge_margin;
  const int width = img.cols - 2 * m, height = img.rows - 2 * m;
  if (width < 8 || height < 8) return;

  // Scores over the region and a one-pixel ring around it (the suppression neighbourhood).
  const int sw = width + 2, sh = height + 2;
  scratch->scores.resize(static_cast<size_t>(sw) * sh);
  uint8_t* scores = scratch->scores.data();
  ComputeFastScores(img, m - 1, m - 1, m - 1 + sw, m - 1 + sh, scores, sw);

  const int cells_x = std::max(1, width / o.cell_size), cells_y = std::max(1, height / o.cell_size);
  const int cell_w = (width + cells_x - 1) / cells_x, cell_h = (height + cells_y - 1) / cells_y;
  std::vector<uint8_t>& strong = scratch->cell_has_strong;
  strong.assign(static_cast<size_t>(cells_x) * cells_y, 0);
  const int low = o.min_fast_threshold, high = o.fast_threshold;
  for (int y = 1; y <= height; ++y) {
    const uint8_t* above = scores + (y - 1) * sw;
    const uint8_t* row = scores + y * sw;
    const uint8_t* below = scores + (y + 1) * sw;
    const int cy = std::min((y - 1) / cell_h, cells_y - 1);
    for (int x = 1; x <= width; ++x) {
      // Skip 8 weak pixels at once.
      if (x + 8 <= width + 1) {
        uint64_t block;
        std::memcpy(&block, row + x, 8);
        // A byte exceeds `low` (< 128) when adding 127 - low sets its top bit (or it already has it).
        const uint64_t lanes = 0x0101010101010101ull;
        if (!((((block & (0x7f * lanes)) + (127 - low) * lanes) | block) & (0x80 * lanes))) {
          x += 7;
          continue;
        }
      }
      const int s = row[x];
      if (s <= low) continue;
      // Earlier neighbours (raster order) must be strictly weaker, later ones not stronger.
      if (s <= above[x - 1] || s <= above[x] || s <= above[x + 1] || s <= row[x - 1]) continue;
      if (s < row[x + 1] || s < below[x - 1] || s < below[x] || s < below[x + 1]) continue;
      out->push_back({static_cast<int16_t>(x - 1 + m), static_cast<int16_t>(y - 1 + m), static_cast<float>(s)});
      if (s > high) strong[static_cast<size_t>(cy) * cells_x + std::min((x - 1) / cell_w, cells_x - 1)] = 1;
    }
  }
  // Keep strong corners everywhere and weak ones only where a cell has no strong corner.
  size_t kept = 0;
  for (const Candidate& c : *out) {
    const int cx = std::min((c.x - m) / cell_w, cells_x - 1), cy = std::min((c.y - m) / cell_h, cells_y - 1);
    if (c.response > high || !strong[static_cast<size_t>(cy) * cells_x + cx]) (*out)[kept++] = c;
  }
  out->resize(kept);
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
// weights holds, per row v = -15..15, 32 column weights over x-15 .. x+16: u inside the disc
// (else 0), then 32 membership flags; fixed-length rows vectorise.
float CentroidAngle(const cv::Mat& img, int x, int y, const int16_t* weights) {
  const ptrdiff_t step = static_cast<ptrdiff_t>(img.step1());
  const uint8_t* top_left = img.ptr<uint8_t>(y - kOrientationRadius) + x - kOrientationRadius;
  int m10 = 0, m01 = 0;
  for (int v = 0; v < 2 * kOrientationRadius + 1; ++v) {
    const uint8_t* row = top_left + v * step;
    const int16_t* wu = weights + v * 64;
    const int16_t* inside = wu + 32;
    int sum_u = 0, sum = 0;
    for (int i = 0; i < 32; ++i) {
      sum_u += wu[i] * row[i];
      sum += inside[i] * row[i];
    }
    m10 += sum_u;
    m01 += (v - kOrientationRadius) * sum;
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

// Learned by OrbExtractor.DISABLED_LearnPattern (see LearnedBriefPattern()).
constexpr int8_t kLearnedPattern[256][4] = {
    {-7, 0, -8, 8}, {6, -4, 8, 10}, {-8, 3, -7, -4}, {7, 2, 8, -7},
    {-2, -3, -2, -13}, {3, -10, 3, 1}, {-1, -3, -1, 1}, {-2, 13, -1, -9},
    {-8, -11, -6, -8}, {11, 4, 13, 1}, {-1, 4, -1, -1}, {-7, 12, -5, 9},
    {-7, -4, -7, -7}, {-9, 2, -7, 2}, {4, 12, 4, 5}, {-12, -3, -14, 4},
    {-10, -10, -8, -11}, {9, 8, 11, 9}, {7, -9, 7, -5}, {-11, 0, -14, -3},
    {4, -13, 4, -9}, {-3, 4, -3, 7}, {12, -9, 13, -7}, {-8, 8, -7, 10},
    {4, 11, 5, 13}, {2, 8, 2, -6}, {11, -2, 14, -5}, {12, -2, 14, 4},
    {-3, 11, -2, 13}, {-13, -7, -13, -2}, {6, -10, 9, -12}, {-2, -10, 0, -11},
    {5, 5, 7, 0}, {6, -1, 8, -1}, {-6, 1, -3, 1}, {-3, -3, -1, -6},
    {13, 7, 12, 9}, {-8, -6, -1, 11}, {0, -15, -7, 11}, {0, 7, 3, 7},
    {-5, -14, 2, 11}, {8, 12, 6, 12}, {0, 12, 6, -9}, {5, -4, 2, -4},
    {1, -13, 10, 4}, {4, -5, -12, 6}, {5, 2, -7, -4}, {-8, -10, 7, 12},
    {7, -13, -6, 4}, {-11, 10, 12, -7}, {-13, -6, 9, -5}, {-14, 0, 13, 6},
    {-8, -7, 12, 1}, {-10, 3, 9, -1}, {-14, 4, -11, 10}, {-5, 7, -6, -13},
    {-12, -8, -11, -10}, {-10, 6, -11, 8}, {11, 7, 11, 4}, {1, -13, 2, 13},
    {-2, -11, -2, -14}, {9, -12, 11, -10}, {-4, -4, -4, -2}, {-1, -11, 1, 6},
    {4, -2, 5, 1}, {-6, 7, -2, -6}, {14, -1, 10, -4}, {7, 13, 12, -4},
    {1, 8, 0, 5}, {1, -4, 0, -6}, {5, 4, 4, 2}, {11, 5, 7, 3},
    {2, 5, -1, 2}, {2, 14, 0, 13}, {12, -9, 2, 3}, {-3, -6, 4, 11},
    {-5, 14, 6, -4}, {-3, -1, 11, 8}, {11, -4, -4, 7}, {-10, -1, 8, 9},
    {9, 6, -10, -8}, {-14, -2, -9, -5}, {-12, -1, -9, 4}, {-10, 11, -8, -10},
    {0, 0, 0, 15}, {-13, 7, -7, 9}, {5, 7, 5, 3}, {-9, -5, -6, -3},
    {-5, -5, -5, 14}, {-3, 8, -3, 10}, {-13, 3, -13, 5}, {3, -7, 4, -10},
    {-6, -10, -4, -13}, {6, -5, 7, -3}, {4, 10, 7, -13}, {-4, -7, -2, -6},
    {-1, 14, 1, 11}, {8, -5, 12, -4}, {-7, 7, -3, 7}, {-4, 3, -5, -1},
    {-10, 2, -4, -12}, {4, 5, 6, 7}, {0, -15, 2, -13}, {4, -10, 6, -10},
    {3, 13, 6, 9}, {-3, 1, -1, 1}, {-1, 1, 1, -1}, {3, 4, 5, 3},
    {-11, -9, 1, 4}, {4, -9, -1, 5}, {7, 12, 1, -9}, {-2, -8, 7, 5},
    {3, -13, -9, 1}, {-8, 11, 5, -10}, {15, 0, -2, 13}, {9, 10, -4, -14},
    {6, -8, -9, -2}, {-14, 5, 12, -1}, {-7, 6, 14, 4}, {-11, 4, 9, -9},
    {14, -3, -7, -1}, {-11, -2, 10, 2}, {8, -3, 9, 0}, {11, -9, 11, 0},
    {-4, 5, -3, 2}, {-2, 10, -1, -14}, {-11, -6, -12, -8}, {-7, -7, -6, -11},
    {-2, -7, -1, 8}, {-6, 3, -5, 5}, {10, 11, 9, 7}, {1, -5, 1, -9},
    {-3, 4, -2, -9}, {3, 2, 3, 0}, {-1, 9, 0, 7}, {-9, -3, -6, -5},
    {4, -3, 5, -6}, {-12, 9, -3, -2}, {5, 0, 6, -2}, {-9, -12, -4, 13},
    {1, 6, 2, 3}, {5, -11, 7, 7}, {1, -9, 1, -11}, {-4, 2, -8, -4},
    {6, 9, 8, 6}, {-3, -8, -4, -10}, {2, 13, 1, 9}, {1, -1, 3, -4},
    {-3, 13, 0, 13}, {-1, -10, 1, -8}, {-6, 13, -7, 10}, {14, 5, 10, 4},
    {-3, 7, -1, 8}, {9, -1, 8, 3}, {-3, -2, 0, 11}, {8, -7, 8, -12},
    {1, -4, -2, 10}, {5, -5, 10, -7}, {13, 5, 9, -12}, {4, 7, 2, -14},
    {-2, 14, -14, 2}, {9, 3, 7, 0}, {-1, -9, -3, -6}, {-4, 8, 1, -10},
    {0, -4, 2, -4}, {5, -5, 3, -11}, {0, 15, -5, -9}, {11, -4, 6, -11},
    {-6, 0, 1, 6}, {-8, 9, 2, 0}, {-7, 3, 3, 14}, {4, -2, -7, -12},
    {1, -1, 14, -1}, {-13, -5, 4, 11}, {-3, -14, 8, -5}, {4, 7, -5, -10},
    {10, -11, -2, 9}, {-3, 2, 8, -6}, {-6, 6, 5, -6}, {-9, 5, 6, 5},
    {11, -7, -4, -6}, {9, 7, -7, 10}, {-6, -13, 12, 4}, {-6, 1, 9, 3},
    {11, 5, -5, -6}, {-9, 8, 11, 0}, {12, -5, -12, 0}, {12, 8, 13, -5},
    {-10, -8, -7, 5}, {3, -9, 4, 14}, {-5, 10, -4, -9}, {-8, 1, -14, 4},
    {-5, -11, -3, 1}, {-6, 9, -4, 5}, {8, 2, 9, 5}, {7, 6, 8, 9},
    {-1, 1, 0, -10}, {-7, 3, -6, 1}, {-14, -5, -8, 11}, {9, 4, 11, 3},
    {10, -1, 11, -3}, {-4, 1, -3, -2}, {2, 13, 3, -3}, {-7, -9, -5, -9},
    {-10, -11, -11, 2}, {-10, -4, -10, -2}, {2, -1, 4, 10}, {-5, -12, -2, -13},
    {1, -4, 2, -6}, {-7, 5, -9, 1}, {-8, 9, -9, 4}, {0, 8, 3, -13},
    {1, -7, 3, 4}, {3, 5, 6, -9}, {-6, 1, -3, 13}, {5, -14, 7, 0},
    {5, 8, 7, 8}, {-4, -3, -2, -3}, {-2, 6, -6, -8}, {-8, 11, -1, 13},
    {4, 11, 7, -4}, {13, -7, 11, -7}, {3, -11, 0, 15}, {2, -11, 4, -10},
    {1, -13, 0, -11}, {4, -1, 6, -1}, {5, 3, 13, -3}, {7, -12, 2, 0},
    {0, -15, 4, -1}, {-1, 2, 5, 14}, {14, 1, 8, 9}, {0, -14, -4, 3},
    {0, -7, -7, 13}, {-4, -6, 1, 3}, {-1, -14, -11, -5}, {-2, -12, 4, -14},
    {3, -1, 11, 10}, {4, -7, 12, 5}, {5, -4, 4, -6}, {-11, 0, 0, -5},
    {-4, 12, 3, -14}, {0, 11, 6, 2}, {-10, 8, 1, -10}, {0, 5, -2, 6},
    {-1, -5, 5, -10}, {1, -6, -4, 4}, {-5, -5, 2, -6}, {5, -3, 0, 7},
    {7, 12, 0, 15}, {9, 3, 4, 3}, {-1, -3, 6, 8}, {2, 8, 12, 0},
    {9, -8, 3, -14}, {-1, 0, 7, 0}, {1, -8, 10, -2}, {-1, -10, 11, 10},
};

}  // namespace

BriefPattern GaussianBriefPairs(uint64_t seed, int count, double sigma) {
  FLATSLAM_CHECK(count >= 0 && sigma > 0, "GaussianBriefPairs: bad count ", count, " or sigma ", sigma);
  const int r = kBriefPatternRadius;
  // Pairs inside the disc are at most ~(pi r^2)^2 / 2; stay far below so the draw terminates.
  FLATSLAM_CHECK(count <= 200000, "GaussianBriefPairs: count ", count, " too large");
  SplitMix64 rng{seed};
  auto draw_point = [&](int* x, int* y) {
    while (true) {
      *x = static_cast<int>(std::lround(sigma * rng.Gaussian()));
      *y = static_cast<int>(std::lround(sigma * rng.Gaussian()));
      if ((*x) * (*x) + (*y) * (*y) <= r * r) return;
    }
  };
  // A pair and its swap are one test (up to the bit's sign): key on the ordered form.
  const auto key = [](int x1, int y1, int x2, int y2) {
    const int a = (y1 + 16) * 33 + (x1 + 16), b = (y2 + 16) * 33 + (x2 + 16);
    return a < b ? a * 2048 + b : b * 2048 + a;
  };
  std::unordered_set<int> seen;
  BriefPattern pattern;
  pattern.reserve(count);
  while (static_cast<int>(pattern.size()) < count) {
    int x1, y1, x2, y2;
    draw_point(&x1, &y1);
    draw_point(&x2, &y2);
    if ((x1 - x2) * (x1 - x2) + (y1 - y2) * (y1 - y2) < 4) continue;
    const int k = key(x1, y1, x2, y2);
    if (!seen.insert(k).second) continue;
    pattern.push_back({static_cast<int8_t>(x1), static_cast<int8_t>(y1), static_cast<int8_t>(x2),
                       static_cast<int8_t>(y2)});
  }
  return pattern;
}

const BriefPattern& LearnedBriefPattern() {
  static const BriefPattern pattern = [] {
    BriefPattern p;
    for (const auto& pair : kLearnedPattern) p.push_back({pair[0], pair[1], pair[2], pair[3]});
    return p;
  }();
  return pattern;
}

bool OrbOptions::Check() const {
  return features >= 1 && levels >= 1 && levels <= 32 && (scale_factor > 1.f || levels == 1) &&
         fast_threshold >= 1 && fast_threshold <= 127 && min_fast_threshold >= 1 &&
         min_fast_threshold <= fast_threshold &&
         cell_size >= 8 && edge_margin >= kOrientationRadius + 1 && edge_margin <= 1000 && blur_sigma >= 0 &&
         blur_kernel >= 1 && blur_kernel % 2 == 1 && blur_kernel <= 31;
}

void FastScores(const cv::Mat& gray, cv::Mat* scores) {
  FLATSLAM_CHECK(!gray.empty() && gray.type() == CV_8UC1, "FastScores: image must be a non-empty CV_8UC1");
  FLATSLAM_CHECK(scores != nullptr, "FastScores: null output");
  scores->create(gray.size(), CV_8UC1);
  scores->setTo(0);
  if (gray.cols < 7 || gray.rows < 7) return;
  ComputeFastScores(gray, 3, 3, gray.cols - 3, gray.rows - 3, scores->ptr<uint8_t>(3) + 3, scores->step1());
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
  pattern_ = options.pattern_seed == 0 ? LearnedBriefPattern() : GaussianBriefPairs(options.pattern_seed, kDescriptorBits);
  // Disc u^2 + v^2 <= (r + 1/2)^2: symmetric under 90-degree rotations and mirroring.
  const int r = kOrientationRadius;
  orientation_weights_.assign((2 * r + 1) * 64, 0);
  for (int v = -r; v <= r; ++v) {
    for (int u = -r; u <= r; ++u) {
      if (u * u + v * v > (r + 0.5) * (r + 0.5)) continue;
      orientation_weights_[(v + r) * 64 + (u + r)] = static_cast<int16_t>(u);
      orientation_weights_[(v + r) * 64 + 32 + (u + r)] = 1;
    }
  }
  blur_taps_ = GaussianTaps(options.blur_kernel, options.blur_sigma);
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
    Scratch scratch;
    for (int l = range.begin(); l != range.end(); ++l) {
      DetectCorners(pyramid->levels[l], options_, &scratch, &results[l].corners);
    }
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
    Scratch scratch;
    std::vector<Candidate>& kept = scratch.kept;
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
        r.angle[i] = CentroidAngle(img, r.corners[i].x, r.corners[i].y, orientation_weights_.data());
      }
      cv::Mat blurred = img;
      if (blur_taps_.size() > 1) {
        Blur(img, blur_taps_, &scratch.blurred, &scratch.blur_row, &scratch.blur_acc);
        blurred = scratch.blurred;
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
