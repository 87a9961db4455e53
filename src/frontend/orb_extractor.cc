#include "frontend/orb_extractor.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <numeric>
#include <unordered_set>

#include <opencv2/imgproc.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

#include "core/cpu_features.h"
#include "core/error.h"
#include "core/requirements.h"

// Vector-extension helpers are always inlined; their by-value ABI never crosses a call.
#pragma GCC diagnostic ignored "-Wpsabi"

namespace flatslam {
namespace {

constexpr int kDescriptorBits = 256;

// A FAST corner on one level, level coordinates.
struct Candidate {
  int16_t x, y;
  uint16_t score;  // FAST score
  uint16_t unused = 0;
  // Orders by score, then earlier position: larger key = preferred (a branch-free comparison).
  [[nodiscard]] uint64_t key() const {
    return (uint64_t{score} << 32) | (uint64_t{static_cast<uint16_t>(~y)} << 16) | static_cast<uint16_t>(~x);
  }
};

// A quadtree cell: region [x0,x1) x [y0,y1) and its candidates [begin, end) of the level array.
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

// ---- Pixel kernels ------------------------------------------------------------------------
// A pixel's FAST score is the largest, over the 16 arcs of 9 contiguous pixels of the radius-3
// circle, of the smallest difference to the centre along the arc, on the brighter or the darker
// side. So the pixel is a FAST-9 corner at threshold t (all 9 brighter than centre + t or all
// darker than centre - t) exactly when score > t: one pass serves every threshold.
//
// Kernels exist for the x86-64 baseline (SSE2) and for AVX2, picked at run time: FAST scores and
// suppression are written once with GCC/Clang vector extensions (32 pixels per step: two SSE2
// registers or one AVX2 register) and compiled twice; blur, orientation and BRIEF have AVX2
// intrinsics versions. All give identical results (the same integer and float operations), as
// OrbExtractor.VectorAndBaselineKernelsAgree checks.

// The radius-3 Bresenham circle, clockwise from the top.
constexpr int kCircle[16][2] = {{0, -3}, {1, -3}, {2, -2}, {3, -1}, {3, 0},  {3, 1},   {2, 2},   {1, 3},
                                {0, 3},  {-1, 3}, {-2, 2}, {-3, 1}, {-3, 0}, {-3, -1}, {-2, -2}, {-1, -3}};

using Bytes32 = uint8_t __attribute__((vector_size(32)));

[[gnu::always_inline]] inline Bytes32 Load32(const uint8_t* p) {
  Bytes32 v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}
[[gnu::always_inline]] inline Bytes32 Min32(Bytes32 a, Bytes32 b) {
  return a < b ? a : b;
}
[[gnu::always_inline]] inline Bytes32 Max32(Bytes32 a, Bytes32 b) {
  return a > b ? a : b;
}
// Lanes of a > b (unsigned) as 0xff / 0, from min and equality: cheap without unsigned compares.
[[gnu::always_inline]] inline Bytes32 Greater32(Bytes32 a, Bytes32 b) {
  return reinterpret_cast<Bytes32>(Min32(a, b) != a);
}
[[gnu::always_inline]] inline bool Any32(Bytes32 v) {
  uint64_t w[4];
  std::memcpy(w, &v, sizeof(w));
  return (w[0] | w[1] | w[2] | w[3]) != 0;
}
// Bit i set when byte i of a 0xff / 0 mask is set.
[[gnu::always_inline]] inline uint32_t MoveMask32(Bytes32 v) {
  uint64_t w[4];
  std::memcpy(w, &v, sizeof(w));
  uint32_t bits = 0;
  for (int i = 0; i < 4; ++i) {
    // Gathers the top bit of each byte into the top byte (no carries: one bit per byte).
    bits |= static_cast<uint32_t>(((w[i] & 0x8080808080808080ull) * 0x0002040810204081ull) >> 56) << (8 * i);
  }
  return bits;
}

// max over k of min(d[k], ..., d[k+8]) (indices mod 16). For even k, M = min(d[k+1..k+8]) serves
// the arcs starting at k and k+1: max(min(d[k], M), min(M, d[k+9])) = min(M, max(d[k], d[k+9])).
// M comes from minima of pairs and quadruples at odd starts: 48 vector operations in all.
[[gnu::always_inline]] inline Bytes32 BestArc(const Bytes32 (&d)[16]) {
  Bytes32 m2[16], m4[16];
  for (int j = 1; j < 16; j += 2) m2[j] = Min32(d[j], d[(j + 1) & 15]);
  for (int j = 1; j < 16; j += 2) m4[j] = Min32(m2[j], m2[(j + 2) & 15]);
  Bytes32 best = {};
  for (int k = 0; k < 16; k += 2) {
    const Bytes32 m8 = Min32(m4[k + 1], m4[(k + 5) & 15]);
    best = Max32(best, Min32(m8, Max32(d[k], d[(k + 9) & 15])));
  }
  return best;
}

// Pointer offsets of the radius-3 circle's 16 pixels in an image of row stride `step`.
void CircleOffsets(ptrdiff_t step, ptrdiff_t* offsets) {
  for (int k = 0; k < 16; ++k) offsets[k] = kCircle[k][1] * step + kCircle[k][0];
}

// Scalar version of the same score (narrow images).
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
// row stride is out_step and whose first element is pixel (x0, y0). Scores <= floor may be
// written as 0: a block of 32 is skipped when no pixel can exceed floor, i.e. when no two
// neighbouring compass points (circle 0, 4, 8, 12) both differ by more than floor on one side,
// which any 9-arc above floor would need.
[[gnu::always_inline]] inline void FastScoresBody(const cv::Mat& img, int x0, int y0, int x1, int y1, int floor,
                                                  uint8_t* out, size_t out_step) {
  const ptrdiff_t step = static_cast<ptrdiff_t>(img.step1());
  ptrdiff_t offsets[16];
  CircleOffsets(step, offsets);
  const Bytes32 floor32 = Bytes32{} + static_cast<uint8_t>(floor);
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
      if (floor > 0) {
        Bytes32 bright[4], dark[4];
        for (int q = 0; q < 4; ++q) {
          const Bytes32 v = Load32(p + offsets[4 * q]);
          const Bytes32 lo = Min32(v, c);
          bright[q] = Greater32(v - lo, floor32);
          dark[q] = Greater32(c - lo, floor32);
        }
        const Bytes32 possible = (bright[0] & bright[1]) | (bright[1] & bright[2]) | (bright[2] & bright[3]) |
                                 (bright[3] & bright[0]) | (dark[0] & dark[1]) | (dark[1] & dark[2]) |
                                 (dark[2] & dark[3]) | (dark[3] & dark[0]);
        if (!Any32(possible)) {
          std::memset(dst + x, 0, 32);
          if (x + 32 >= count) break;
          continue;
        }
      }
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

using Bytes8 = uint8_t __attribute__((vector_size(8)));
using Words8 = uint16_t __attribute__((vector_size(16)));

// dst[x] = (128 + sum_k taps[k] * src[k][x]) / 256 for x in [0, count): one output row of a
// separable pass, 8 pixels per step in 16-bit lanes (one SSE2 register; the plain loop is not
// vectorised by the compiler).
void BlurLine(const uint8_t* const* src, const uint16_t* taps, int size, int count, uint8_t* dst) {
  if (count < 8) {
    for (int x = 0; x < count; ++x) {
      int acc = 128;
      for (int k = 0; k < size; ++k) acc += taps[k] * src[k][x];
      dst[x] = static_cast<uint8_t>(acc >> 8);
    }
    return;
  }
  for (int x = 0;; x += 8) {
    if (x + 8 > count) x = count - 8;  // last block overlaps the previous one
    Words8 acc = Words8{} + 128;
    for (int k = 0; k < size; ++k) {
      Bytes8 v;
      std::memcpy(&v, src[k] + x, sizeof(v));
      acc += taps[k] * __builtin_convertvector(v, Words8);
    }
    const Bytes8 out = __builtin_convertvector(acc >> 8, Bytes8);
    std::memcpy(dst + x, &out, sizeof(out));
    if (x + 8 >= count) break;
  }
}

using BlurLineFn = void (*)(const uint8_t* const*, const uint16_t*, int, int, uint8_t*);

// Separable blur with integer taps summing to 256 (so sums fit 16 bits) and reflect-101
// borders. row is scratch for one padded intermediate row.
void BlurRows(const cv::Mat& src, const std::vector<uint16_t>& taps, BlurLineFn line, cv::Mat* dst,
              std::vector<uint8_t>* row) {
  const int cols = src.cols, rows = src.rows, size = static_cast<int>(taps.size()), r = size / 2;
  dst->create(rows, cols, CV_8UC1);
  row->resize(cols + 2 * r);
  uint8_t* padded = row->data();
  const auto reflect = [](int i, int n) {
    while (i < 0 || i >= n) i = i < 0 ? -i : 2 * (n - 1) - i;
    return i;
  };
  const uint8_t* lines[32];
  for (int y = 0; y < rows; ++y) {
    for (int k = 0; k < size; ++k) lines[k] = src.ptr<uint8_t>(reflect(y + k - r, rows));
    line(lines, taps.data(), size, cols, padded + r);
    for (int j = 1; j <= r; ++j) {
      padded[r - j] = padded[r + reflect(j, cols)];
      padded[r + cols - 1 + j] = padded[r + reflect(cols - 1 - j, cols)];
    }
    for (int k = 0; k < size; ++k) lines[k] = padded + k;
    line(lines, taps.data(), size, cols, dst->ptr<uint8_t>(y));
  }
}

// Appends the local maxima above `threshold` among score rows [y0, y1) x columns [x0, x1) (a
// one-pixel ring of scores around them exists; the row stride is `stride`, at least 34).
// Earlier neighbours in raster order must be strictly weaker, later ones not stronger, so a
// plateau keeps its first pixel. Candidates get (x + x_offset, y + y_offset), raster order.
[[gnu::always_inline]] inline void SuppressBody(const uint8_t* scores, int stride, int x0, int y0, int x1, int y1,
                                                int threshold, int x_offset, int y_offset,
                                                std::vector<Candidate>* out) {
  const Bytes32 threshold32 = Bytes32{} + static_cast<uint8_t>(threshold);
  // Blocks of 32 columns; the last one is moved left (inside the ring) and earlier columns
  // dropped, so a narrow range still reads whole blocks.
  const int last_start = std::max(1, std::min(x1, stride - 1) - 32);
  for (int y = y0; y < y1; ++y) {
    const uint8_t* above = scores + (y - 1) * stride;
    const uint8_t* row = scores + y * stride;
    const uint8_t* below = scores + (y + 1) * stride;
    for (int start = x0; start < x1; start += 32) {
      const int x = std::min(start, last_start);
      // Vector test against the largest neighbour; ties (rare) are resolved one by one.
      const Bytes32 s = Load32(row + x);
      const Bytes32 neighbours = Max32(
          Max32(Max32(Load32(above + x - 1), Load32(above + x)), Max32(Load32(above + x + 1), Load32(row + x - 1))),
          Max32(Max32(Load32(row + x + 1), Load32(below + x - 1)), Max32(Load32(below + x), Load32(below + x + 1))));
      uint32_t bits = MoveMask32(Greater32(s, threshold32) & ~Greater32(neighbours, s));
      while (bits != 0) {
        const int cx = x + std::countr_zero(bits);
        bits &= bits - 1;
        if (cx < start || cx >= x1 || cx >= start + 32) continue;
        const uint8_t v = row[cx];
        if (v == above[cx - 1] || v == above[cx] || v == above[cx + 1] || v == row[cx - 1]) continue;
        out->push_back({static_cast<int16_t>(cx + x_offset), static_cast<int16_t>(y + y_offset), v});
      }
    }
  }
}

// Runtime dispatch: the same bodies compiled for AVX2 where the CPU has it.
#if defined(__x86_64__) || defined(__i386__)
__attribute__((target("avx2"))) void FastScoresAvx2(const cv::Mat& img, int x0, int y0, int x1, int y1, int floor,
                                                    uint8_t* out, size_t out_step) {
  FastScoresBody(img, x0, y0, x1, y1, floor, out, out_step);
}
// Same arithmetic as BlurLine, 32 pixels per step. With taps below 128, pmaddubsw weighs two
// taps per instruction (a pair sums to at most 255 * 254, no saturation); 16-bit totals wrap
// but stay below 65536, so the final logical shift is exact.
__attribute__((target("avx2"))) void BlurLineAvx2(const uint8_t* const* src, const uint16_t* taps, int size, int count,
                                                  uint8_t* dst) {
  if (count < 32) return BlurLine(src, taps, size, count, dst);
  const bool small_taps = std::all_of(taps, taps + size, [](uint16_t t) { return t < 128; });
  const __m256i zero = _mm256_setzero_si256(), half = _mm256_set1_epi16(128);
  __m256i weights[32];
  const int pairs = (size + 1) / 2;
  for (int k = 0; k < size; ++k) weights[k] = _mm256_set1_epi16(static_cast<int16_t>(taps[k]));
  for (int p = 0; p < pairs && small_taps; ++p) {
    const int second = 2 * p + 1 < size ? taps[2 * p + 1] : 0;
    weights[p] = _mm256_set1_epi16(static_cast<int16_t>(taps[2 * p] | (second << 8)));  // bytes: w0, w1
  }
  for (int x = 0;; x += 32) {
    if (x + 32 > count) x = count - 32;  // last block overlaps the previous one
    __m256i lo = half, hi = half;        // pixels 0-7 and 16-23, 8-15 and 24-31 (in-lane unpack)
    if (small_taps) {
      for (int p = 0; p < pairs; ++p) {
        const __m256i a = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(src[2 * p] + x));
        const __m256i b =
            2 * p + 1 < size ? _mm256_loadu_si256(reinterpret_cast<const __m256i*>(src[2 * p + 1] + x)) : zero;
        lo = _mm256_add_epi16(lo, _mm256_maddubs_epi16(_mm256_unpacklo_epi8(a, b), weights[p]));
        hi = _mm256_add_epi16(hi, _mm256_maddubs_epi16(_mm256_unpackhi_epi8(a, b), weights[p]));
      }
    } else {
      for (int k = 0; k < size; ++k) {
        const __m256i v = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(src[k] + x));
        lo = _mm256_add_epi16(lo, _mm256_mullo_epi16(_mm256_unpacklo_epi8(v, zero), weights[k]));
        hi = _mm256_add_epi16(hi, _mm256_mullo_epi16(_mm256_unpackhi_epi8(v, zero), weights[k]));
      }
    }
    // The in-lane pack undoes the in-lane unpack: pixels come back in order.
    const __m256i out = _mm256_packus_epi16(_mm256_srli_epi16(lo, 8), _mm256_srli_epi16(hi, 8));
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(dst + x), out);
    if (x + 32 >= count) break;
  }
}
__attribute__((target("avx2"))) void SuppressAvx2(const uint8_t* scores, int stride, int x0, int y0, int x1, int y1,
                                                  int threshold, int x_offset, int y_offset,
                                                  std::vector<Candidate>* out) {
  SuppressBody(scores, stride, x0, y0, x1, y1, threshold, x_offset, y_offset, out);
}
#endif

void ComputeFastScores(bool avx2, const cv::Mat& img, int x0, int y0, int x1, int y1, int floor, uint8_t* out,
                       size_t out_step) {
#if defined(__x86_64__) || defined(__i386__)
  if (avx2) return FastScoresAvx2(img, x0, y0, x1, y1, floor, out, out_step);
#endif
  FastScoresBody(img, x0, y0, x1, y1, floor, out, out_step);
}

void Blur(bool avx2, const cv::Mat& src, const std::vector<uint16_t>& taps, cv::Mat* dst, std::vector<uint8_t>* row) {
#if defined(__x86_64__) || defined(__i386__)
  if (avx2) return BlurRows(src, taps, BlurLineAvx2, dst, row);
#endif
  BlurRows(src, taps, BlurLine, dst, row);
}

void Suppress(bool avx2, const uint8_t* scores, int stride, int x0, int y0, int x1, int y1, int threshold, int x_offset,
              int y_offset, std::vector<Candidate>* out) {
#if defined(__x86_64__) || defined(__i386__)
  if (avx2) return SuppressAvx2(scores, stride, x0, y0, x1, y1, threshold, x_offset, y_offset, out);
#endif
  SuppressBody(scores, stride, x0, y0, x1, y1, threshold, x_offset, y_offset, out);
}

// Integer Gaussian taps summing to exactly 256 (rounding remainder to the centre tap).
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

// Sub-pixel position of each corner: per axis, the vertex of the parabola through the FAST scores
// at -1, 0, +1 pixels. A corner is a 3x3 maximum of the score, so the vertex lies within half a
// pixel; it stays 0 where the score is flat. Integer positions quantize a keypoint to +-0.5 level
// pixels (0.29 px RMS), which on a coarse level or a small image is most of the measurement noise.
void SubpixelOffsets(const cv::Mat& img, const std::vector<Candidate>& corners, Eigen::Vector2f* offsets) {
  const ptrdiff_t step = static_cast<ptrdiff_t>(img.step1());
  ptrdiff_t circle[16];
  CircleOffsets(step, circle);
  const auto vertex = [](int minus, int centre, int plus) {
    const int curvature = minus + plus - 2 * centre;
    if (curvature >= 0) return 0.f;
    return std::clamp(0.5f * static_cast<float>(minus - plus) / static_cast<float>(curvature), -0.5f, 0.5f);
  };
  for (size_t i = 0; i < corners.size(); ++i) {
    const uint8_t* p = img.ptr<uint8_t>(corners[i].y) + corners[i].x;
    const int c = corners[i].score;
    offsets[i] = {vertex(FastScoreAt(p - 1, circle), c, FastScoreAt(p + 1, circle)),
                  vertex(FastScoreAt(p - step, circle), c, FastScoreAt(p + step, circle))};
  }
}

// Per-level scratch, owned by one work item.
}  // namespace

struct ExtractorScratch {
  std::vector<uint8_t> scores;
  std::vector<uint8_t> cell_has_strong;
  std::vector<Candidate> kept;
  std::vector<Node> nodes, next_nodes;
  std::vector<Candidate> sort_buffer;
  std::vector<uint8_t> blurred_pixels;  // backs `blurred` for any level size
  cv::Mat blurred;
  std::vector<uint8_t> blur_row;
};

namespace {
using Scratch = ExtractorScratch;

// FAST corners in [m, cols-m) x [m, rows-m) of a level, after 3x3 non-maximum suppression
// (ties go to the first in raster order): those above the high threshold, then, cell by cell,
// those above the low one in grid cells without any (textureless areas still get corners).
void DetectCorners(bool avx2, const cv::Mat& img, const OrbOptions& o, Scratch* scratch, std::vector<Candidate>* out) {
  out->clear();
  const int m = o.edge_margin;
  const int width = img.cols - 2 * m, height = img.rows - 2 * m;
  if (width < 32 || height < 8) return;  // a level this small holds no useful keypoint

  // Scores over the region and a one-pixel ring around it (the suppression neighbourhood).
  const int sw = width + 2, sh = height + 2;
  const int low = o.min_fast_threshold, high = o.fast_threshold;
  scratch->scores.resize(static_cast<size_t>(sw) * sh);
  uint8_t* scores = scratch->scores.data();
  ComputeFastScores(avx2, img, m - 1, m - 1, m - 1 + sw, m - 1 + sh, low, scores, sw);

  // Score-buffer coordinates: region pixel (x, y) is at (x + 1, y + 1); image = buffer + m - 1.
  Suppress(avx2, scores, sw, 1, 1, width + 1, height + 1, high, m - 1, m - 1, out);
  if (low >= high) return;
  const int cells_x = std::max(1, width / o.cell_size), cells_y = std::max(1, height / o.cell_size);
  const int cell_w = (width + cells_x - 1) / cells_x, cell_h = (height + cells_y - 1) / cells_y;
  std::vector<uint8_t>& strong = scratch->cell_has_strong;
  strong.assign(static_cast<size_t>(cells_x) * cells_y, 0);
  for (const Candidate& c : *out) {
    const int cx = std::min((c.x - m) / cell_w, cells_x - 1), cy = std::min((c.y - m) / cell_h, cells_y - 1);
    strong[static_cast<size_t>(cy) * cells_x + cx] = 1;
  }
  for (int cy = 0; cy < cells_y; ++cy) {
    for (int cx = 0; cx < cells_x; ++cx) {
      if (strong[static_cast<size_t>(cy) * cells_x + cx]) continue;
      const int x0 = cx * cell_w, y0 = cy * cell_h;
      const int x1 = std::min(x0 + cell_w, width), y1 = std::min(y0 + cell_h, height);
      if (x0 < x1 && y0 < y1) Suppress(avx2, scores, sw, x0 + 1, y0 + 1, x1 + 1, y1 + 1, low, m - 1, m - 1, out);
    }
  }
}

// Splits a node into its non-empty quarters: a branch-free, stable counting sort of its
// candidates by quarter (through tmp), so unpredictable comparisons cost nothing.
void SplitNode(const Node& n, std::vector<Candidate>* pts, std::vector<Candidate>* tmp, std::vector<Node>* children) {
  const float xm = 0.5f * (n.x0 + n.x1), ym = 0.5f * (n.y0 + n.y1);
  Candidate* p = pts->data();
  const auto quarter = [xm, ym](const Candidate& c) { return (c.y >= ym) * 2 + (c.x >= xm); };
  uint32_t count[4] = {0, 0, 0, 0};
  for (uint32_t i = n.begin; i < n.end; ++i) ++count[quarter(p[i])];
  uint32_t start[4] = {n.begin, n.begin + count[0], n.begin + count[0] + count[1],
                       n.begin + count[0] + count[1] + count[2]};
  const uint32_t begins[4] = {start[0], start[1], start[2], start[3]};
  tmp->resize(pts->size());
  Candidate* t = tmp->data();
  for (uint32_t i = n.begin; i < n.end; ++i) t[start[quarter(p[i])]++] = p[i];
  std::copy(t + n.begin, t + n.end, p + n.begin);
  const Node quarters[4] = {{n.x0, n.y0, xm, ym, begins[0], begins[0] + count[0]},
                            {xm, n.y0, n.x1, ym, begins[1], begins[1] + count[1]},
                            {n.x0, ym, xm, n.y1, begins[2], begins[2] + count[2]},
                            {xm, ym, n.x1, n.y1, begins[3], begins[3] + count[3]}};
  for (const Node& q : quarters) {
    if (q.count() > 0) children->push_back(q);
  }
}

// Keeps at most `budget` candidates spread over the region: quarters cells (largest first once
// close to the budget) until there are `budget` non-empty cells, then keeps each cell's strongest.
// The result depends only on the set of candidates, not their order. Output sorted by (y, x).
void Distribute(std::vector<Candidate>* pts, float x0, float y0, float x1, float y1, int budget,
                std::vector<Node>* nodes, std::vector<Node>* next, std::vector<Candidate>* tmp,
                std::vector<Candidate>* out) {
  out->clear();
  if (budget <= 0 || pts->empty()) return;
  const auto by_position = [](const Candidate& a, const Candidate& b) { return a.y != b.y ? a.y < b.y : a.x < b.x; };
  if (static_cast<int>(pts->size()) <= budget) {
    *out = *pts;
    std::sort(out->begin(), out->end(), by_position);
    return;
  }

  // Start from roughly square cells: a wide image begins with several columns, a tall one rows.
  const float w = x1 - x0, h = y1 - y0;
  const int nx = std::max(1, static_cast<int>(std::lround(w / h)));
  const int ny = std::max(1, static_cast<int>(std::lround(h / w)));
  nodes->clear();
  {
    auto row_begin = pts->begin();
    for (int j = 0; j < ny; ++j) {
      const float ya = y0 + h * j / ny, yb = j + 1 == ny ? y1 : y0 + h * (j + 1) / ny;
      const auto row_end = j + 1 == ny
                               ? pts->end()
                               : std::partition(row_begin, pts->end(), [yb](const Candidate& c) { return c.y < yb; });
      auto col_begin = row_begin;
      for (int i = 0; i < nx; ++i) {
        const float xa = x0 + w * i / nx, xb = i + 1 == nx ? x1 : x0 + w * (i + 1) / nx;
        const auto col_end =
            i + 1 == nx ? row_end : std::partition(col_begin, row_end, [xb](const Candidate& c) { return c.x < xb; });
        const Node n{xa,
                     ya,
                     xb,
                     yb,
                     static_cast<uint32_t>(col_begin - pts->begin()),
                     static_cast<uint32_t>(col_end - pts->begin())};
        if (n.count() > 0) nodes->push_back(n);
        col_begin = col_end;
      }
      row_begin = row_end;
    }
  }

  std::vector<uint32_t> order;
  while (static_cast<int>(nodes->size()) < budget) {
    size_t expandable = 0;
    for (const Node& n : *nodes) expandable += n.splittable();
    if (expandable == 0) break;
    next->clear();
    if (nodes->size() + 3 * expandable <= static_cast<size_t>(budget)) {
      // A full round cannot overshoot: split every cell.
      for (const Node& n : *nodes) {
        if (n.splittable()) {
          SplitNode(n, pts, tmp, next);
        } else {
          next->push_back(n);
        }
      }
    } else {
      // Last round: split the most crowded cells first and stop at the budget. Cells are in a
      // geometric order, so ties break the same way whatever the candidates' order.
      order.clear();
      for (uint32_t i = 0; i < nodes->size(); ++i) {
        if ((*nodes)[i].splittable()) order.push_back(i);
      }
      std::sort(order.begin(), order.end(), [&](uint32_t a, uint32_t b) {
        const uint32_t ca = (*nodes)[a].count(), cb = (*nodes)[b].count();
        return ca != cb ? ca > cb : a < b;
      });
      size_t count = nodes->size();
      size_t split_until = 0;  // order[0, split_until) are split
      std::vector<Node> children;
      for (; split_until < order.size() && count < static_cast<size_t>(budget); ++split_until) {
        const size_t before = children.size();
        SplitNode((*nodes)[order[split_until]], pts, tmp, &children);
        count += children.size() - before - 1;
      }
      std::vector<uint8_t> split(nodes->size(), 0);
      for (size_t k = 0; k < split_until; ++k) split[order[k]] = 1;
      for (uint32_t i = 0; i < nodes->size(); ++i) {
        if (!split[i]) next->push_back((*nodes)[i]);
      }
      next->insert(next->end(), children.begin(), children.end());
    }
    nodes->swap(*next);
  }

  out->reserve(nodes->size());
  const auto stronger = [](const Candidate& a, const Candidate& b) { return a.key() > b.key(); };
  const Candidate* p = pts->data();
  for (const Node& n : *nodes) {
    uint64_t best = 0;
    uint32_t best_index = n.begin;
    for (uint32_t k = n.begin; k < n.end; ++k) {
      const uint64_t key = p[k].key();
      best_index = key > best ? k : best_index;
      best = std::max(best, key);
    }
    out->push_back(p[best_index]);
  }
  if (static_cast<int>(out->size()) > budget) {
    std::nth_element(out->begin(), out->begin() + budget, out->end(), stronger);
    out->resize(budget);
  }
  std::sort(out->begin(), out->end(), by_position);
}

// Direction of the intensity centroid of the disc around (x, y): atan2(m01, m10), radians.
// weights holds, per row v = -15..15, 32 column weights over x-15 .. x+16: u inside the disc
// (else 0), then 32 membership flags; fixed-length rows vectorise.
float CentroidAngle(const cv::Mat& img, int x, int y, const int8_t* weights) {
  const ptrdiff_t step = static_cast<ptrdiff_t>(img.step1());
  const uint8_t* top_left = img.ptr<uint8_t>(y - kOrientationRadius) + x - kOrientationRadius;
  int m10 = 0, m01 = 0;
  for (int v = 0; v < 2 * kOrientationRadius + 1; ++v) {
    const uint8_t* row = top_left + v * step;
    const int8_t* wu = weights + v * 64;
    const int8_t* inside = wu + 32;
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

// The pattern as float columns x1, y1, x2, y2 (256 each) for the rotation.
struct PatternColumns {
  alignas(32) float v[4][kDescriptorBits];
};

// Rounds to nearest by truncating a value shifted positive (the same in scalar and vector code).
inline int RoundShifted(float v) {
  return static_cast<int>(v + 64.5f) - 64;
}

// Steered BRIEF on the blurred level: the pattern rotated by `angle`, points rounded to pixels.
Descriptor SteeredBrief(const cv::Mat& blurred, int x, int y, float angle, const PatternColumns& pattern) {
  const uint8_t* center = blurred.ptr<uint8_t>(y) + x;
  const int step = static_cast<int>(blurred.step1());
  const float c = std::cos(angle), s = std::sin(angle);
  const float *px1 = pattern.v[0], *py1 = pattern.v[1], *px2 = pattern.v[2], *py2 = pattern.v[3];
  alignas(64) int off1[kDescriptorBits], off2[kDescriptorBits];
  for (int k = 0; k < kDescriptorBits; ++k) {
    off1[k] = RoundShifted(px1[k] * s + py1[k] * c) * step + RoundShifted(px1[k] * c - py1[k] * s);
    off2[k] = RoundShifted(px2[k] * s + py2[k] * c) * step + RoundShifted(px2[k] * c - py2[k] * s);
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

// Angles (on the level image) and descriptors (on its blurred copy) of a level's corners.
void DescribeCornersBaseline(const cv::Mat& img, const cv::Mat& blurred, const std::vector<Candidate>& corners,
                             const int8_t* weights, const PatternColumns& pattern, float* angles,
                             Descriptor* descriptors) {
  for (size_t i = 0; i < corners.size(); ++i) {
    angles[i] = CentroidAngle(img, corners[i].x, corners[i].y, weights);
    descriptors[i] = SteeredBrief(blurred, corners[i].x, corners[i].y, angles[i], pattern);
  }
}

#if defined(__x86_64__) || defined(__i386__)
// Pixel offsets of 8 pattern points rotated by (c, s): RoundShifted on each coordinate, with the
// same float operations as the baseline (no FMA), so both round alike.
__attribute__((target("avx2"))) inline __m256i RotatedOffsetsAvx2(const float* px, const float* py, __m256 c, __m256 s,
                                                                  __m256i step8) {
  const __m256 ax = _mm256_load_ps(px), ay = _mm256_load_ps(py);
  const __m256 shift = _mm256_set1_ps(64.5f);
  const __m256i sixty_four = _mm256_set1_epi32(64);
  const __m256i rx = _mm256_sub_epi32(
      _mm256_cvttps_epi32(_mm256_add_ps(_mm256_sub_ps(_mm256_mul_ps(ax, c), _mm256_mul_ps(ay, s)), shift)), sixty_four);
  const __m256i ry = _mm256_sub_epi32(
      _mm256_cvttps_epi32(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ax, s), _mm256_mul_ps(ay, c)), shift)), sixty_four);
  return _mm256_add_epi32(_mm256_mullo_epi32(ry, step8), rx);
}

// Same sums and tests as the baseline: pmaddubsw for the moments, 8 tests per gather. Rows are
// read 32 bytes (x-15 .. x+16) and gathers 4 bytes: both stay inside the image as keypoints keep
// edge_margin >= 16 from borders (and are never on the last rows).
__attribute__((target("avx2"))) void DescribeCornersAvx2(const cv::Mat& img, const cv::Mat& blurred,
                                                         const std::vector<Candidate>& corners, const int8_t* weights,
                                                         const PatternColumns& pattern, float* angles,
                                                         Descriptor* descriptors) {
  const ptrdiff_t img_step = static_cast<ptrdiff_t>(img.step1());
  const int step = static_cast<int>(blurred.step1());
  const __m256i ones16 = _mm256_set1_epi16(1), byte_mask = _mm256_set1_epi32(0xff);
  const __m256i step8 = _mm256_set1_epi32(step);
  for (size_t i = 0; i < corners.size(); ++i) {
    const int x = corners[i].x, y = corners[i].y;
    // Intensity centroid.
    const uint8_t* top_left = img.ptr<uint8_t>(y - kOrientationRadius) + x - kOrientationRadius;
    __m256i m10 = _mm256_setzero_si256(), m01 = _mm256_setzero_si256();
    for (int v = 0; v < 2 * kOrientationRadius + 1; ++v) {
      const __m256i row = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(top_left + v * img_step));
      const __m256i wu = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(weights + v * 64));
      const __m256i inside = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(weights + v * 64 + 32));
      m10 = _mm256_add_epi32(m10, _mm256_madd_epi16(_mm256_maddubs_epi16(row, wu), ones16));
      const __m256i dv = _mm256_set1_epi16(static_cast<int16_t>(v - kOrientationRadius));
      m01 = _mm256_add_epi32(m01, _mm256_madd_epi16(_mm256_maddubs_epi16(row, inside), dv));
    }
    alignas(32) int lanes10[8], lanes01[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes10), m10);
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes01), m01);
    int s10 = 0, s01 = 0;
    for (int k = 0; k < 8; ++k) {
      s10 += lanes10[k];
      s01 += lanes01[k];
    }
    const float angle = std::atan2(static_cast<float>(s01), static_cast<float>(s10));
    angles[i] = angle;

    // Steered BRIEF.
    const uint8_t* center = blurred.ptr<uint8_t>(y) + x;
    const __m256 c = _mm256_set1_ps(std::cos(angle)), s = _mm256_set1_ps(std::sin(angle));
    Descriptor d{};
    for (int k = 0; k < kDescriptorBits; k += 8) {
      const __m256i off1 = RotatedOffsetsAvx2(pattern.v[0] + k, pattern.v[1] + k, c, s, step8);
      const __m256i off2 = RotatedOffsetsAvx2(pattern.v[2] + k, pattern.v[3] + k, c, s, step8);
      const __m256i a =
          _mm256_and_si256(_mm256_i32gather_epi32(reinterpret_cast<const int*>(center), off1, 1), byte_mask);
      const __m256i b =
          _mm256_and_si256(_mm256_i32gather_epi32(reinterpret_cast<const int*>(center), off2, 1), byte_mask);
      const uint32_t bits = static_cast<uint32_t>(_mm256_movemask_ps(_mm256_castsi256_ps(_mm256_cmpgt_epi32(b, a))));
      d[k / 64] |= static_cast<uint64_t>(bits) << (k % 64);
    }
    descriptors[i] = d;
  }
}
#endif

void DescribeCorners(bool avx2, const cv::Mat& img, const cv::Mat& blurred, const std::vector<Candidate>& corners,
                     const int8_t* weights, const PatternColumns& pattern, float* angles, Descriptor* descriptors) {
#if defined(__x86_64__) || defined(__i386__)
  if (avx2) return DescribeCornersAvx2(img, blurred, corners, weights, pattern, angles, descriptors);
#endif
  DescribeCornersBaseline(img, blurred, corners, weights, pattern, angles, descriptors);
}

// What one level produces.
struct LevelResult {
  std::vector<Candidate> corners;  // all FAST candidates, then the kept ones
  std::vector<Eigen::Vector2f> offset;  // sub-pixel offset of each kept corner (level pixels); empty: none
  std::vector<float> angle;
  std::vector<Descriptor> descriptor;
};

// Learned by OrbExtractor.DISABLED_LearnPattern (see LearnedBriefPattern()).
constexpr int8_t kLearnedPattern[256][4] = {
    {-12, 9, -5, 0},    {-5, 3, -5, -6},     {-10, 4, -11, -9},  {3, -11, 3, -1},    {10, 8, 10, -4},
    {-6, 6, -6, 10},    {-2, 13, -1, -7},    {10, -1, 12, 0},    {-3, -5, -3, -8},   {-1, 4, -1, -1},
    {-12, 1, -9, 4},    {4, -3, 5, 10},      {4, 13, 4, 6},      {-1, -3, -1, 1},    {9, 8, 11, 9},
    {9, -10, 9, 2},     {4, -13, 4, -9},     {-8, -11, -6, -8},  {-11, -9, -9, -12}, {-12, -3, -15, 0},
    {-6, 3, -5, 5},     {0, 8, 0, -11},      {-2, -11, -2, -14}, {-3, 11, -2, 13},   {9, -12, 11, -10},
    {5, 0, 6, -2},      {6, -10, 9, -12},    {-11, 9, -12, 5},   {-3, -14, 0, -14},  {5, 5, 7, 2},
    {4, 13, 7, 13},     {-10, -5, -4, 14},   {0, -11, 2, -10},   {3, 2, 5, 4},       {13, -7, 11, -7},
    {-3, -5, -1, -5},   {-3, -5, -4, -3},    {12, 6, 10, 10},    {-1, 3, 1, 4},      {0, -15, -7, 11},
    {3, 4, 2, 6},       {10, -2, 7, -1},     {6, -7, 4, -7},     {-14, 5, 5, -13},   {5, 10, -4, -8},
    {-3, 6, 14, 3},     {-10, 11, 7, -4},    {-12, -7, 7, 5},    {-6, -4, 13, -5},   {7, -9, -8, 1},
    {12, 9, -8, -9},    {-12, 1, 11, -1},    {-2, 2, -2, 8},     {-14, -5, -8, -6},  {12, 2, 15, 0},
    {-3, -8, -2, -11},  {-9, -4, -7, -8},    {-7, 10, -8, 12},   {-7, 9, -5, 10},    {4, 10, 7, -13},
    {4, -4, 5, -1},     {-5, 4, -3, 3},      {-15, 0, -14, 2},   {0, 10, -1, 6},     {-1, -5, 1, -3},
    {0, 7, -2, 9},      {8, -5, 7, -7},      {0, -14, 5, 8},     {2, -5, 0, -4},     {-6, 7, 2, -10},
    {-10, -2, 3, 2},    {-6, 13, 8, -12},    {-4, -1, 9, 10},    {9, 4, -4, -11},    {-11, 7, 15, 0},
    {8, 0, -7, 4},      {11, 6, -10, 0},     {7, 1, 8, 4},       {-4, -13, -3, 9},   {-12, 2, -14, 5},
    {-8, -3, -8, 8},    {12, -9, 13, -7},    {4, -8, 4, 6},      {4, 11, 5, 13},     {7, 6, 8, 9},
    {-11, -6, -12, -8}, {11, -5, 12, -3},    {-9, -3, -8, -1},   {3, -7, 4, -10},    {-8, -7, -4, -4},
    {11, 3, 12, 6},     {2, -11, 1, 13},     {-4, 14, -1, 10},   {13, -1, 14, 2},    {6, -2, 8, 1},
    {-6, -2, -3, 3},    {0, -5, 2, 8},       {-6, -3, -9, 1},    {4, 5, 6, 7},       {13, 1, 11, 5},
    {-5, -11, -7, -8},  {6, 12, 10, 8},      {5, -14, 9, 8},     {11, -7, 8, -4},    {-6, -8, -1, 11},
    {1, 3, 4, -2},      {-2, 14, 4, 14},     {0, 3, -2, 5},      {0, 15, 6, -4},     {0, -1, 7, -10},
    {2, 9, -7, -12},    {-7, 3, 3, 14},      {0, 8, 11, -10},    {3, -6, -5, 12},    {1, -12, 11, -1},
    {-10, 5, 7, 9},     {-10, -11, 9, -6},   {-13, -3, 10, -11}, {-7, 8, 11, -6},    {-8, -7, 12, 1},
    {-6, 11, -4, -4},   {-1, 0, -1, -12},    {-13, 7, -8, 10},   {-5, 0, -6, -12},   {3, 4, 3, 0},
    {-3, -5, -2, 7},    {5, -2, 6, -6},      {-5, 1, -5, 3},     {-12, 4, -11, -1},  {1, -6, 1, -8},
    {-9, 10, -5, -10},  {-13, -4, -11, -1},  {1, -2, 0, 11},     {-13, -6, -4, 6},   {-11, -10, -12, -7},
    {8, -5, 12, -4},    {7, -7, 12, 6},      {7, 3, 9, 2},       {-9, -5, -9, -3},   {-3, -2, -4, -4},
    {-4, 11, -4, 9},    {-3, -9, 0, 4},      {-3, -8, -4, -10},  {9, -1, 9, 1},      {11, -4, 11, -7},
    {14, 5, 10, 4},     {8, -7, 8, -12},     {-3, 7, -1, 8},     {-14, 2, -2, -12},  {-7, -2, -2, -3},
    {-3, -14, -6, -11}, {6, 10, 14, -3},     {1, 9, 3, 9},       {0, 6, 4, -12},     {-2, 14, -5, -1},
    {-3, 2, 0, -3},     {7, 13, 3, -11},     {4, -14, 8, -11},   {10, 6, 7, 3},      {-2, -10, 2, 12},
    {-4, 2, -1, 4},     {5, -6, 4, -9},      {15, 0, 8, -12},    {2, -4, 4, -3},     {0, -6, -9, 8},
    {2, -7, 11, 10},    {-1, -8, 5, 5},      {-4, -14, 4, 2},    {7, -1, 4, -2},     {2, 4, 11, -5},
    {-7, -3, 3, -14},   {3, -8, -10, -7},    {-4, -12, 7, 13},   {-13, -5, 4, 11},   {-4, 5, 5, -7},
    {4, 8, -6, -1},     {-4, 13, 12, 6},     {-11, 4, 5, -5},    {10, 5, -2, -5},    {13, -1, -2, 0},
    {6, 10, -10, -11},  {-6, 5, 9, -12},     {9, -5, -3, 9},     {6, -2, -7, -4},    {7, 1, -14, -1},
    {8, 12, -10, -4},   {-13, -7, 13, -4},   {-14, -4, 13, 5},   {-12, 5, 10, -7},   {11, 3, -13, 4},
    {13, 1, -8, 1},     {10, 2, -9, -3},     {-12, 1, -8, -1},   {7, 8, 7, 3},       {2, -5, 2, -2},
    {-5, 13, -3, 2},    {-1, -13, -1, 14},   {-8, -1, -7, 1},    {-8, -9, -6, 7},    {1, -12, 1, -7},
    {10, 0, 12, -5},    {-15, 0, -9, -12},   {6, 4, 6, -2},      {-10, 6, -11, 8},   {-8, 4, -6, 4},
    {-6, 6, -5, 2},     {-6, 13, -4, 12},    {0, 14, 1, 3},      {0, 5, 1, -7},      {-14, -3, -14, 1},
    {-3, 5, -2, -11},   {1, 5, 1, 3},        {-13, -7, -13, -2}, {0, -6, 0, -4},     {-11, 9, -13, -4},
    {3, 8, 3, 6},       {-11, -10, -5, -10}, {1, -7, 3, 14},     {3, -2, 4, 2},      {6, 6, 9, -8},
    {8, 0, 8, -3},      {-8, 12, -9, 1},     {-3, -8, -5, 8},    {6, -5, 8, -5},     {1, 7, 3, 11},
    {-1, -9, 2, -14},   {-3, 6, -6, 9},      {1, 9, 4, -7},      {1, 11, 0, 14},     {5, 13, 8, -5},
    {2, -10, 4, -8},    {-2, 0, 1, -6},      {-9, -12, 0, -1},   {-2, -9, 1, -10},   {-4, -2, -1, -1},
    {-4, 12, 1, -11},   {-10, -1, -2, 9},    {2, -11, 0, -15},   {1, 1, 4, 1},       {6, 13, 1, 1},
    {-2, -14, -7, -1},  {7, 3, 4, -10},      {6, 6, 4, 10},      {6, -11, 4, -9},    {-1, -2, 2, 1},
    {-3, -1, 2, 11},    {3, 0, 14, 4},       {2, 6, 7, 5},       {11, 1, 5, -7},     {-6, -6, 1, 7},
    {8, 9, 5, 8},       {1, 11, -5, 11},     {2, -1, -7, 10},    {-10, 3, 2, 7},     {0, 13, 15, 0},
    {6, -9, -2, -7},
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
    pattern.push_back(
        {static_cast<int8_t>(x1), static_cast<int8_t>(y1), static_cast<int8_t>(x2), static_cast<int8_t>(y2)});
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

void FastScores(const cv::Mat& gray, cv::Mat* scores) {
  FLATSLAM_CHECK(!gray.empty() && gray.type() == CV_8UC1, "FastScores: image must be a non-empty CV_8UC1");
  FLATSLAM_CHECK(scores != nullptr, "FastScores: null output");
  scores->create(gray.size(), CV_8UC1);
  scores->setTo(0);
  if (gray.cols < 7 || gray.rows < 7) return;
  ComputeFastScores(HasAvx2(), gray, 3, 3, gray.cols - 3, gray.rows - 3, 0, scores->ptr<uint8_t>(3) + 3,
                    scores->step1());
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
                 options.levels, ", scale_factor ", options.scale_factor, ", thresholds ", options.fast_threshold, "/",
                 options.min_fast_threshold, ", edge_margin ", options.edge_margin, ")");
  std::vector<double> weights;
  for (int i = 0; i < options.levels; ++i) {
    weights.push_back(options.budget_by_area ? scales_.inv_sigma2[i] : scales_.inv_scale[i]);
  }
  level_budget_ = Apportion(options.features, weights);
  pattern_ =
      options.pattern_seed == 0 ? LearnedBriefPattern() : GaussianBriefPairs(options.pattern_seed, kDescriptorBits);
  // Disc u^2 + v^2 <= (r + 1/2)^2: symmetric under 90-degree rotations and mirroring.
  const int r = kOrientationRadius;
  orientation_weights_.assign((2 * r + 1) * 64, 0);
  for (int v = -r; v <= r; ++v) {
    for (int u = -r; u <= r; ++u) {
      if (u * u + v * v > (r + 0.5) * (r + 0.5)) continue;
      orientation_weights_[(v + r) * 64 + (u + r)] = static_cast<int8_t>(u);
      orientation_weights_[(v + r) * 64 + 32 + (u + r)] = 1;
    }
  }
  blur_taps_ = GaussianTaps(options.blur_kernel, options.blur_sigma);
  scratch_ = std::make_shared<ObjectPool<ExtractorScratch>>();
}

void OrbExtractor::BuildPyramid(const cv::Mat& gray, ImagePyramid* pyramid) const {
  FLATSLAM_CHECK(!gray.empty(), "OrbExtractor: empty image");
  FLATSLAM_CHECK(gray.type() == CV_8UC1, "OrbExtractor: image must be CV_8UC1 (gray), got type ", gray.type());
  FLATSLAM_CHECK(pyramid != nullptr, "OrbExtractor: null pyramid");
  FLATSLAM_CHECK(gray.cols < 32768 && gray.rows < 32768, "OrbExtractor: image too large (", gray.cols, "x", gray.rows,
                 "), at most 32767 pixels a side");
  pyramid->levels.resize(options_.levels);
  pyramid->levels[0] = gray;
  for (int i = 1; i < options_.levels; ++i) {
    const cv::Size size(std::max(1, static_cast<int>(std::lround(gray.cols * scales_.inv_scale[i]))),
                        std::max(1, static_cast<int>(std::lround(gray.rows * scales_.inv_scale[i]))));
    cv::resize(pyramid->levels[i - 1], pyramid->levels[i], size, 0, 0, cv::INTER_LINEAR);
  }
}

void OrbExtractor::BlurLevel(const cv::Mat& level, cv::Mat* blurred) const {
  FLATSLAM_CHECK(!level.empty() && level.type() == CV_8UC1, "OrbExtractor: level must be a non-empty CV_8UC1");
  FLATSLAM_CHECK(blurred != nullptr, "OrbExtractor: null output");
  if (blur_taps_.size() == 1) {
    level.copyTo(*blurred);
    return;
  }
  std::vector<uint8_t> row;
  Blur(options_.use_avx2 && HasAvx2(), level, blur_taps_, blurred, &row);
}

void OrbExtractor::Extract(const cv::Mat& gray, Keypoints* out) const {
  ImagePyramid pyramid;
  Extract(gray, out, &pyramid);
}

void OrbExtractor::Extract(const cv::Mat& gray, Keypoints* out, ImagePyramid* pyramid) const {
  FLATSLAM_CHECK(out != nullptr, "OrbExtractor: null output");
  BuildPyramid(gray, pyramid);
  const int levels = options_.levels;
  const bool avx2 = options_.use_avx2 && HasAvx2();
  std::vector<LevelResult> results(levels);

  // 1. Candidates per level.
  tbb::parallel_for(tbb::blocked_range<int>(0, levels, 1), [&](const tbb::blocked_range<int>& range) {
    const auto scratch = scratch_->Acquire();
    for (int l = range.begin(); l != range.end(); ++l) {
      DetectCorners(avx2, pyramid->levels[l], options_, scratch.get(), &results[l].corners);
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
  PatternColumns pattern;
  for (int k = 0; k < kDescriptorBits; ++k) {
    for (int j = 0; j < 4; ++j) pattern.v[j][k] = pattern_[k][j];
  }
  const int m = options_.edge_margin;
  tbb::parallel_for(tbb::blocked_range<int>(0, levels, 1), [&](const tbb::blocked_range<int>& range) {
    const auto lease = scratch_->Acquire();
    Scratch& scratch = *lease;
    std::vector<Candidate>& kept = scratch.kept;
    for (int l = range.begin(); l != range.end(); ++l) {
      LevelResult& r = results[l];
      const cv::Mat& img = pyramid->levels[l];
      Distribute(&r.corners, static_cast<float>(m), static_cast<float>(m), static_cast<float>(img.cols - m),
                 static_cast<float>(img.rows - m), take[l], &scratch.nodes, &scratch.next_nodes, &scratch.sort_buffer,
                 &kept);
      r.corners.swap(kept);
      r.angle.resize(r.corners.size());
      r.descriptor.resize(r.corners.size());
      if (r.corners.empty()) continue;
      cv::Mat blurred = img;
      if (blur_taps_.size() > 1) {
        // A header over pooled pixels: Blur's create() then finds the size it needs in place.
        const size_t pixels = static_cast<size_t>(img.rows) * img.cols;
        if (scratch.blurred_pixels.size() < pixels) scratch.blurred_pixels.resize(pixels);
        scratch.blurred = cv::Mat(img.rows, img.cols, CV_8UC1, scratch.blurred_pixels.data());
        Blur(avx2, img, blur_taps_, &scratch.blurred, &scratch.blur_row);
        blurred = scratch.blurred;
      }
      DescribeCorners(avx2, img, blurred, r.corners, orientation_weights_.data(), pattern, r.angle.data(),
                      r.descriptor.data());
      if (options_.subpixel) {
        r.offset.resize(r.corners.size());
        SubpixelOffsets(img, r.corners, r.offset.data());
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
      const Eigen::Vector2f corner(r.corners[i].x, r.corners[i].y);
      out->uv[k] = pyramid->FromLevel(r.offset.empty() ? corner : Eigen::Vector2f(corner + r.offset[i]), l);
      out->angle[k] = r.angle[i];
      out->octave[k] = static_cast<uint8_t>(l);
      out->response[k] = r.corners[i].score;
      out->descriptor[k] = r.descriptor[i];
    }
  }
}

}  // namespace flatslam
