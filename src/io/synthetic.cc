// Synthetic renderer: z-buffered planar quads with mip-mapped procedural textures.
#include "io/synthetic.h"

#include <algorithm>
#include <array>
#include <bit>
#include <cmath>
#include <iterator>
#include <limits>
#include <random>
#include <sstream>
#include <utility>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

#include <opencv2/imgproc.hpp>
#include <tbb/parallel_for.h>

#include "core/cpu_features.h"
#include "core/error.h"

namespace flatslam {

SceneQuad MakeQuad(const Eigen::Vector3d& origin, const Eigen::Vector3d& u, const Eigen::Vector3d& v,
                   double texels_per_m, float brightness) {
  SceneQuad q;
  q.origin = origin;
  q.size_u = u.norm();
  q.size_v = v.norm();
  q.axis_u = u / q.size_u;
  q.axis_v = v / q.size_v;
  q.texels_per_m = texels_per_m;
  q.brightness = brightness;
  return q;
}
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr int kMaxTextureSide = 4096;
constexpr float kNearPlane = 0.05f;

// SplitMix64: the state steps by kSplitMixStep; the output mixes the new state with two multiplies.
constexpr uint64_t kSplitMixStep = 0x9e3779b97f4a7c15ull;
constexpr uint64_t kSplitMixMul1 = 0xbf58476d1ce4e5b9ull, kSplitMixMul2 = 0x94d049bb133111ebull;

uint64_t SplitMix(uint64_t* state) {
  uint64_t z = (*state += kSplitMixStep);
  z = (z ^ (z >> 30)) * kSplitMixMul1;
  z = (z ^ (z >> 27)) * kSplitMixMul2;
  return z ^ (z >> 31);
}

// Approximately standard normal from four uniform bytes (Irwin-Hall); cheap and deterministic.
float GaussFromBits(uint64_t bits) {
  const int sum = static_cast<int>(bits & 0xff) + static_cast<int>((bits >> 8) & 0xff) +
                  static_cast<int>((bits >> 16) & 0xff) + static_cast<int>((bits >> 24) & 0xff);
  return (static_cast<float>(sum) - 510.0f) * (1.0f / 147.8f);
}

// The exact depth image read with independent noise per pixel (sigma = k z^2) and nothing beyond
// max_depth.
void NoisyDepth(float k, float max_depth, uint64_t* rng, cv::Mat* depth) {
  for (int v = 0; v < depth->rows; ++v) {
    float* d = depth->ptr<float>(v);
    for (int u = 0; u < depth->cols; ++u) {
      const float z = d[u];
      if (z <= 0 || z > max_depth) {
        d[u] = 0;
        continue;
      }
      d[u] = std::max(0.0f, z + k * z * z * GaussFromBits(SplitMix(rng)));
    }
  }
}

// A structured-light sensor's reading of the exact depth image (see SyntheticOptions::
// structured_light); `fx` is the colour camera's, to which the depth image is registered, and
// noise_k the depth noise (sigma = k z^2), applied as disparity noise before quantization.
void StructuredLightDepth(double fx, float noise_k, uint64_t* rng, cv::Mat* depth) {
  constexpr float kSensorFocalPx = 580, kSensorBaselineM = 0.075f, kDisparityStep = 1.0f / 8, kMaxRangeM = 4.5f;
  constexpr int kFattenRadius = 2, kRegistrationShiftPx = 1;
  constexpr float kFattenStep = 0.05f, kDropout = 0.01f;
  const float inf = std::numeric_limits<float>::infinity();
  cv::Mat z = depth->clone();
  z.setTo(inf, z <= 0);
  // Foreground fattening: where a surface over 5% nearer lies within the window, it is read.
  cv::Mat nearest;
  cv::erode(z, nearest, cv::getStructuringElement(cv::MORPH_RECT, {2 * kFattenRadius + 1, 2 * kFattenRadius + 1}));
  for (int v = 0; v < z.rows; ++v) {
    float* row = z.ptr<float>(v);
    const float* near_row = nearest.ptr<float>(v);
    for (int u = 0; u < z.cols; ++u)
      if (near_row[u] < row[u] * (1 - kFattenStep)) row[u] = near_row[u];
  }
  // Projector shadow (projector to the camera's left, in the image's pixels): a pixel is unlit
  // when a surface to its left is nearer by more than their pixel distance in the projector's
  // parallax, i.e. max over u' < u of (1/z' + u' / (fx b)) exceeds 1/z + u / (fx b).
  const float fb = static_cast<float>(fx) * kSensorBaselineM;
  cv::Mat out(z.rows, z.cols, CV_32FC1, cv::Scalar(0));
  for (int v = 0; v < z.rows; ++v) {
    const float* row = z.ptr<float>(v);
    float* o = out.ptr<float>(v);
    float reach = -inf;
    for (int u = 0; u < z.cols; ++u) {
      const float inv = std::isfinite(row[u]) ? 1 / row[u] : 0;
      const float here = inv + static_cast<float>(u) / fb;
      const bool shadowed = reach > here + 1e-3f;
      reach = std::max(reach, here);
      // Registered 1 px off: pixel u reads the depth measured for u + shift.
      const int target = u - kRegistrationShiftPx;
      if (target < 0 || shadowed || !std::isfinite(row[u]) || row[u] > kMaxRangeM) continue;
      float disparity = kSensorFocalPx * kSensorBaselineM * inv;
      disparity += kSensorFocalPx * kSensorBaselineM * noise_k * GaussFromBits(SplitMix(rng));
      disparity = std::round(disparity / kDisparityStep) * kDisparityStep;
      if (disparity <= 0) continue;
      if (static_cast<float>(SplitMix(rng) >> 40) * (1.0f / 16777216.0f) < kDropout) continue;
      o[target] = kSensorFocalPx * kSensorBaselineM / disparity;
    }
  }
  *depth = out;
}

// Multi-scale random shapes over smooth noise: corners and blobs at every pyramid scale.
cv::Mat GenerateShapes(int width, int height, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> grey(0, 255), mid(60, 200);
  cv::Mat coarse(std::max(2, height / 40), std::max(2, width / 40), CV_8UC1);
  for (int r = 0; r < coarse.rows; ++r)
    for (int c = 0; c < coarse.cols; ++c) coarse.at<uint8_t>(r, c) = static_cast<uint8_t>(mid(rng));
  cv::Mat img;
  cv::resize(coarse, img, cv::Size(width, height), 0, 0, cv::INTER_CUBIC);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double log_min = std::log(2.0), log_max = std::log(48.0);
  const long shapes = static_cast<long>(width) * height / 300;
  for (long k = 0; k < shapes; ++k) {
    const cv::Point c(static_cast<int>(unit(rng) * width), static_cast<int>(unit(rng) * height));
    const int size = static_cast<int>(std::exp(log_min + unit(rng) * (log_max - log_min)));
    const cv::Scalar colour(grey(rng));
    switch (rng() % 6) {
      case 0:
        cv::rectangle(img, c, c + cv::Point(size, static_cast<int>(size * (0.3 + unit(rng)))), colour, cv::FILLED);
        break;
      case 1:
        cv::circle(img, c, std::max(1, size / 2), colour, cv::FILLED);
        break;
      case 2:
        cv::line(img, c, c + cv::Point(size, static_cast<int>((unit(rng) - 0.5) * 2 * size)), colour,
                 1 + static_cast<int>(rng() % 3));
        break;
      case 3:
        cv::ellipse(img, c, cv::Size(std::max(1, size / 2), std::max(1, size / 4)), unit(rng) * 180, 0, 360, colour,
                    cv::FILLED);
        break;
      case 4: {
        const cv::Point pts[3] = {c, c + cv::Point(size, static_cast<int>(unit(rng) * size)),
                                  c + cv::Point(static_cast<int>(unit(rng) * size), size)};
        cv::fillConvexPoly(img, pts, 3, colour);
        break;
      }
      default:
        cv::rectangle(img, c, c + cv::Point(size, size), colour, 1 + static_cast<int>(rng() % 2));
        break;
    }
  }
  return img;
}

// Smooth noise around mean (+-spread) with cells of about cell texels, plus per-texel grain.
cv::Mat SmoothNoise(int width, int height, double cell, int mean, int spread, int grain, std::mt19937_64* rng) {
  std::uniform_int_distribution<int> level(mean - spread, mean + spread);
  const int cols = std::max(2, static_cast<int>(width / cell)), rows = std::max(2, static_cast<int>(height / cell));
  cv::Mat coarse(rows, cols, CV_8UC1);
  for (int r = 0; r < rows; ++r)
    for (int c = 0; c < cols; ++c) coarse.at<uint8_t>(r, c) = static_cast<uint8_t>(level(*rng));
  cv::Mat img;
  cv::resize(coarse, img, cv::Size(width, height), 0, 0, cv::INTER_CUBIC);
  if (grain > 0) {
    uint64_t state = (*rng)();
    for (int r = 0; r < height; ++r) {
      uint8_t* row = img.ptr<uint8_t>(r);
      for (int c = 0; c < width; ++c) {
        const int g = static_cast<int>(SplitMix(&state) % (2 * grain + 1)) - grain;
        row[c] = static_cast<uint8_t>(std::clamp(row[c] + g, 0, 255));
      }
    }
  }
  return img;
}

// Asphalt: grain over slow variation, with repair patches, cracks and tyre marks along u (metres
// converted with texels_per_m so the features keep their size at any resolution). Every draw is
// its own statement so the texture does not depend on the compiler's argument order.
cv::Mat GenerateAsphalt(int width, int height, double texels_per_m, uint64_t seed) {
  std::mt19937_64 rng(seed);
  cv::Mat img = SmoothNoise(width, height, 1.5 * texels_per_m, 100, 14, 10, &rng);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const double area_m2 = width * height / (texels_per_m * texels_per_m);
  auto texels = [&](double metres) { return std::max(1, static_cast<int>(metres * texels_per_m)); };
  auto at = [&] {
    const int x = static_cast<int>(unit(rng) * width);
    return cv::Point(x, static_cast<int>(unit(rng) * height));
  };
  auto grey = [&](double lo, double span) { return cv::Scalar(lo + span * unit(rng)); };
  for (int k = 0, n = static_cast<int>(area_m2 / 25); k < n; ++k) {  // repair patches
    const cv::Point c = at();
    const int w = texels(0.4 + 2.5 * unit(rng)), h = texels(0.3 + 1.5 * unit(rng));
    cv::rectangle(img, c, c + cv::Point(w, h), grey(60, 70), cv::FILLED);
  }
  for (int k = 0, n = static_cast<int>(area_m2 / 6); k < n; ++k) {  // stains and stones
    const cv::Point c = at();
    const int r = texels(0.03 + 0.25 * unit(rng));
    cv::circle(img, c, r, unit(rng) < 0.5 ? grey(55, 30) : grey(140, 40), cv::FILLED);
  }
  for (int k = 0, n = static_cast<int>(area_m2 / 12); k < n; ++k) {  // cracks: short random walks
    cv::Point p = at();
    for (int step = 0, steps = 3 + static_cast<int>(unit(rng) * 6); step < steps; ++step) {
      const int dx = texels(0.1 + 0.4 * unit(rng)), sx = unit(rng) < 0.5 ? -1 : 1;
      const int dy = texels(0.1 + 0.4 * unit(rng)), sy = unit(rng) < 0.5 ? -1 : 1;
      cv::line(img, p, p + cv::Point(sx * dx, sy * dy), grey(45, 25), 1);
      p += cv::Point(sx * dx, sy * dy);
    }
  }
  for (int k = 0, n = static_cast<int>(area_m2 / 150); k < n; ++k) {  // tyre marks along the road
    const cv::Point c = at();
    const int length = texels(2 + 8 * unit(rng)), width_texels = texels(0.1 + 0.1 * unit(rng));
    cv::ellipse(img, c, cv::Size(length, width_texels), 0, 0, 360, grey(65, 20), cv::FILLED);
  }
  return img;
}

// Road paint: bright with slight grain and a few worn spots.
cv::Mat GeneratePaint(int width, int height, double texels_per_m, uint64_t seed) {
  std::mt19937_64 rng(seed);
  cv::Mat img = SmoothNoise(width, height, 0.5 * texels_per_m, 215, 12, 6, &rng);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int k = 0, n = static_cast<int>(width * height / (texels_per_m * texels_per_m) / 0.5); k < n; ++k) {
    const int x = static_cast<int>(unit(rng) * width), y = static_cast<int>(unit(rng) * height);
    const int r = std::max(1, static_cast<int>(texels_per_m * (0.02 + 0.05 * unit(rng))));
    cv::circle(img, cv::Point(x, y), r, cv::Scalar(120 + 60 * unit(rng)), cv::FILLED);
  }
  return img;
}

cv::Mat GenerateTexture(TextureStyle style, int width, int height, double texels_per_m, uint64_t seed) {
  switch (style) {
    case TextureStyle::kAsphalt:
      return GenerateAsphalt(width, height, texels_per_m, seed);
    case TextureStyle::kPaint:
      return GeneratePaint(width, height, texels_per_m, seed);
    case TextureStyle::kShapes:
      break;
  }
  return GenerateShapes(width, height, seed);
}

// Catmull-Rom point on the closed loop through pts, segment i, parameter u in [0,1].
Eigen::Vector3d CatmullRom(const std::vector<Eigen::Vector3d>& pts, size_t i, double u) {
  const size_t n = pts.size();
  const Eigen::Vector3d& p0 = pts[(i + n - 1) % n];
  const Eigen::Vector3d& p1 = pts[i % n];
  const Eigen::Vector3d& p2 = pts[(i + 1) % n];
  const Eigen::Vector3d& p3 = pts[(i + 2) % n];
  const double u2 = u * u, u3 = u2 * u;
  return 0.5 * ((2 * p1) + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (-p0 + 3 * p1 - 3 * p2 + p3) * u3);
}

}  // namespace

namespace {
// Raw view of one mip level, so the per-pixel sampler touches no cv::Mat internals. Every level
// is followed by at least 4 readable bytes (a padding row): the vector sampler reads a texel and
// its right neighbour as one 32-bit load.
struct TextureLevel {
  const uint8_t* data = nullptr;
  int width = 0, height = 0;
  size_t stride = 0;
  float scale = 1;  // level texels per level-0 texel
};
}  // namespace

struct SyntheticScene::Texture {
  using Level = TextureLevel;
  std::vector<cv::Mat> images;  // CV_8UC1 mip pyramid, level 0 finest (owns the pixels)
  std::vector<Level> levels;
  float texels_per_m = 1;
  // Shading constants of the quad, fixed for the scene's camera.
  float footprint_scale2 = 0;  // (texels_per_m / fx)^2
  float last_level = 0;        // highest level l with l + 1 present
  float brightness = 1;
  float size_u = 0, size_v = 0;
};

// Arc-length table of one agent's loop.
struct SyntheticScene::PathTable {
  std::vector<Eigen::Vector3d> points;
  std::vector<double> arc;  // cumulative length at each point; arc.back() = loop length
  double length = 0;

  explicit PathTable(const std::vector<Eigen::Vector3d>& control) {
    FLATSLAM_CHECK(control.size() >= 4, "camera path needs at least 4 control points");
    constexpr int kSamples = 64;
    for (size_t i = 0; i < control.size(); ++i)
      for (int k = 0; k < kSamples; ++k) points.push_back(CatmullRom(control, i, double(k) / kSamples));
    points.push_back(points.front());
    arc.resize(points.size(), 0.0);
    for (size_t i = 1; i < points.size(); ++i) arc[i] = arc[i - 1] + (points[i] - points[i - 1]).norm();
    length = arc.back();
  }

  [[nodiscard]] Eigen::Vector3d At(double s) const {
    s = std::fmod(s, length);
    if (s < 0) s += length;
    const size_t hi = static_cast<size_t>(std::upper_bound(arc.begin(), arc.end(), s) - arc.begin());
    const size_t i = std::min(hi, arc.size() - 1);
    const size_t j = i == 0 ? 0 : i - 1;
    const double span = arc[i] - arc[j];
    const double f = span > 0 ? (s - arc[j]) / span : 0.0;
    return points[j] + f * (points[i] - points[j]);
  }
};

namespace {

// Per-thread render buffers, reused across frames: per pixel the nearest quad, its inverse depth
// and its homogeneous texture coordinates (s, t) * inverse depth.
struct RenderScratch {
  std::vector<float> inv_depth, s, t;
  std::vector<int32_t> quad;
  void Resize(size_t n) {
    inv_depth.assign(n, 0.0f);
    quad.assign(n, -1);
    s.resize(n);
    t.resize(n);
  }
};

// log2 to within 0.09: exponent plus linear mantissa; enough to choose a mip level.
inline float FastLog2(float x) {
  const uint32_t bits = std::bit_cast<uint32_t>(x);
  const float mantissa = std::bit_cast<float>((bits & 0x007fffffu) | 0x3f800000u);
  return static_cast<float>(static_cast<int>(bits >> 23) - 127) + (mantissa - 1.0f);
}

template <class Level>
[[gnu::always_inline]] inline float SampleBilinear(const Level& img, float x, float y) {
  x = std::clamp(x, 0.0f, static_cast<float>(img.width - 1));
  y = std::clamp(y, 0.0f, static_cast<float>(img.height - 1));
  const int x0 = static_cast<int>(x), y0 = static_cast<int>(y);
  const int x1 = std::min(x0 + 1, img.width - 1), y1 = std::min(y0 + 1, img.height - 1);
  const float fx = x - x0, fy = y - y0;
  const uint8_t* r0 = img.data + img.stride * y0;
  const uint8_t* r1 = img.data + img.stride * y1;
  const float top = r0[x0] + fx * (r0[x1] - r0[x0]);
  const float bottom = r1[x0] + fx * (r1[x1] - r1[x0]);
  return top + fy * (bottom - top);
}

// The sample at level-0 texel coordinates (x0, y0) on one mip level. Levels come from pyrDown,
// whose texel j of level k lies over level-0 texel 2^k j, so a level-0 position x (texel i
// spanning [i, i + 1)) is level index (x - 0.5) 2^-k there, not x 2^-k - 0.5.
template <class Level>
[[gnu::always_inline]] inline float SampleLevel(const Level& level, float x0, float y0) {
  return SampleBilinear(level, (x0 - 0.5f) * level.scale, (y0 - 0.5f) * level.scale);
}

#if defined(__x86_64__) || defined(__i386__)
// What shading a pixel of one quad needs, fixed per quad and view.
struct QuadShading {
  const TextureLevel* levels;
  float footprint_scale2, last_level, brightness, size_u, size_v, texels_per_m;
  float nx, ny, nz;  // the quad's normal in the camera frame
};

// left + fx (right - left) of SampleBilinear, from texel pairs loaded as one 32-bit word per lane
// (left the low byte, right the next unless the lane is at the last column).
__attribute__((target("avx2"))) inline __m256 InterpolateRowAvx2(__m256i both, __m256i has_right, __m256 fx) {
  const __m256i byte = _mm256_set1_epi32(0xff);
  const __m256i left = _mm256_and_si256(both, byte);
  const __m256i right = _mm256_blendv_epi8(left, _mm256_and_si256(_mm256_srli_epi32(both, 8), byte), has_right);
  return _mm256_add_ps(_mm256_cvtepi32_ps(left), _mm256_mul_ps(fx, _mm256_cvtepi32_ps(_mm256_sub_epi32(right, left))));
}

// The bilinear sample of SampleBilinear at eight (x, y), all on one level: the same operations
// in the same order, so the same bits.
__attribute__((target("avx2"))) inline __m256 SampleBilinearAvx2(const TextureLevel& img, __m256 x, __m256 y) {
  const __m256 zero = _mm256_setzero_ps();
  x = _mm256_min_ps(_mm256_max_ps(x, zero), _mm256_set1_ps(static_cast<float>(img.width - 1)));
  y = _mm256_min_ps(_mm256_max_ps(y, zero), _mm256_set1_ps(static_cast<float>(img.height - 1)));
  const __m256i x0 = _mm256_cvttps_epi32(x), y0 = _mm256_cvttps_epi32(y);
  const __m256i y1 = _mm256_min_epi32(_mm256_add_epi32(y0, _mm256_set1_epi32(1)), _mm256_set1_epi32(img.height - 1));
  const __m256 fx = _mm256_sub_ps(x, _mm256_cvtepi32_ps(x0)), fy = _mm256_sub_ps(y, _mm256_cvtepi32_ps(y0));
  // One 32-bit load per row holds the texel (low byte) and its right neighbour; at the last
  // column the neighbour is the texel itself, as in the scalar sampler.
  const __m256i stride = _mm256_set1_epi32(static_cast<int>(img.stride));
  const __m256i row0 = _mm256_i32gather_epi32(reinterpret_cast<const int*>(img.data),
                                              _mm256_add_epi32(_mm256_mullo_epi32(y0, stride), x0), 1);
  const __m256i row1 = _mm256_i32gather_epi32(reinterpret_cast<const int*>(img.data),
                                              _mm256_add_epi32(_mm256_mullo_epi32(y1, stride), x0), 1);
  const __m256i has_right = _mm256_cmpgt_epi32(_mm256_set1_epi32(img.width - 1), x0);
  const __m256 top = InterpolateRowAvx2(row0, has_right, fx), bottom = InterpolateRowAvx2(row1, has_right, fx);
  return _mm256_add_ps(top, _mm256_mul_ps(fy, _mm256_sub_ps(bottom, top)));
}

// The sample at level-0 texel coordinates (x0, y0) on one level, as SampleLevel takes it.
__attribute__((target("avx2"))) inline __m256 SampleLevelAvx2(const TextureLevel& level, __m256 x0, __m256 y0) {
  const __m256 scale = _mm256_set1_ps(level.scale), half = _mm256_set1_ps(0.5f);
  return SampleBilinearAvx2(level, _mm256_mul_ps(_mm256_sub_ps(x0, half), scale),
                            _mm256_mul_ps(_mm256_sub_ps(y0, half), scale));
}

// Shades the `count` (1 to 8) pixels u.. of one row, all of one quad, exactly as the scalar pass
// does (RenderLinear). Lanes past `count` read and write nothing; lanes on different mip levels
// are sampled level by level.
__attribute__((target("avx2"))) void ShadeAvx2(const QuadShading& q, int u, int count, float ry, float cx, float inv_fx,
                                               const float* inv_depth, const float* s_over_w, const float* t_over_w,
                                               float* out, float* dout) {
  const __m256 one = _mm256_set1_ps(1.0f), zero = _mm256_setzero_ps();
  const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
  const __m256i active = _mm256_cmpgt_epi32(_mm256_set1_epi32(count), lane);
  const __m256 uf = _mm256_cvtepi32_ps(_mm256_add_epi32(_mm256_set1_epi32(u), lane));
  const __m256 rx = _mm256_mul_ps(_mm256_sub_ps(uf, _mm256_set1_ps(cx)), _mm256_set1_ps(inv_fx));
  const __m256 ray2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(rx, rx), _mm256_set1_ps(ry * ry)), one);
  const __m256 dot = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(_mm256_set1_ps(q.nx), rx), _mm256_set1_ps(q.ny * ry)),
                                   _mm256_set1_ps(q.nz));
  // Idle lanes get w = 1 and s = t = 0: finite values, so that their (unused) samples stay inside
  // the texture.
  const __m256 w = _mm256_blendv_ps(one, _mm256_maskload_ps(inv_depth, active), _mm256_castsi256_ps(active));
  const __m256 footprint2 =
      _mm256_div_ps(_mm256_mul_ps(_mm256_set1_ps(q.footprint_scale2), ray2),
                    _mm256_mul_ps(_mm256_mul_ps(w, w),
                                  _mm256_max_ps(_mm256_mul_ps(dot, dot), _mm256_mul_ps(_mm256_set1_ps(0.04f), ray2))));
  // FastLog2, lane by lane.
  const __m256i bits = _mm256_castps_si256(footprint2);
  const __m256 exponent = _mm256_cvtepi32_ps(_mm256_sub_epi32(_mm256_srli_epi32(bits, 23), _mm256_set1_epi32(127)));
  const __m256 mantissa = _mm256_castsi256_ps(
      _mm256_or_si256(_mm256_and_si256(bits, _mm256_set1_epi32(0x007fffff)), _mm256_set1_epi32(0x3f800000)));
  const __m256 log2 = _mm256_add_ps(exponent, _mm256_sub_ps(mantissa, one));
  __m256 level = _mm256_and_ps(_mm256_cmp_ps(footprint2, one, _CMP_GT_OQ), _mm256_mul_ps(_mm256_set1_ps(0.5f), log2));
  level = _mm256_min_ps(level, _mm256_set1_ps(q.last_level));
  const __m256i l0 = _mm256_cvttps_epi32(level);
  const __m256 blend = _mm256_min_ps(
      _mm256_max_ps(_mm256_mul_ps(_mm256_sub_ps(_mm256_sub_ps(level, _mm256_cvtepi32_ps(l0)), _mm256_set1_ps(0.3f)),
                                  _mm256_set1_ps(2.5f)),
                    zero),
      one);
  const __m256 inv = _mm256_div_ps(one, w);
  const __m256 s = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(_mm256_maskload_ps(s_over_w, active), inv), zero),
                                 _mm256_set1_ps(q.size_u));
  const __m256 t = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(_mm256_maskload_ps(t_over_w, active), inv), zero),
                                 _mm256_set1_ps(q.size_v));
  const __m256 x0 = _mm256_mul_ps(s, _mm256_set1_ps(q.texels_per_m)),
               y0 = _mm256_mul_ps(t, _mm256_set1_ps(q.texels_per_m));
  const __m256 blending = _mm256_cmp_ps(blend, zero, _CMP_GT_OQ);
  alignas(32) int levels[8];
  _mm256_store_si256(reinterpret_cast<__m256i*>(levels), l0);
  __m256 shaded = zero;
  for (int pending = _mm256_movemask_ps(_mm256_castsi256_ps(active)); pending != 0;) {
    const int l = levels[__builtin_ctz(static_cast<unsigned>(pending))];
    const __m256 on_level =
        _mm256_and_ps(_mm256_castsi256_ps(_mm256_cmpeq_epi32(l0, _mm256_set1_epi32(l))), _mm256_castsi256_ps(active));
    const __m256 a = SampleLevelAvx2(q.levels[l], x0, y0);
    // Where blend is 0 the scalar pass takes b = a; a + 0 * (b - a) is a for any finite b.
    const __m256 b =
        _mm256_movemask_ps(_mm256_and_ps(blending, on_level)) ? SampleLevelAvx2(q.levels[l + 1], x0, y0) : a;
    shaded = _mm256_blendv_ps(
        shaded,
        _mm256_mul_ps(_mm256_add_ps(a, _mm256_mul_ps(blend, _mm256_sub_ps(b, a))), _mm256_set1_ps(q.brightness)),
        on_level);
    pending &= ~_mm256_movemask_ps(on_level);
  }
  _mm256_maskstore_ps(out, active, shaded);
  if (dout) _mm256_maskstore_ps(dout, active, inv);
}

#endif  // x86

// Yaw and pitch offsets of the glance under way at t (raised-cosine turn, hold, turn back).
std::pair<double, double> GlanceOffset(const std::vector<CameraGlance>& glances, double t) {
  const auto next = std::upper_bound(glances.begin(), glances.end(), t,
                                     [](double time, const CameraGlance& g) { return time < g.start_s; });
  if (next == glances.begin()) return {0.0, 0.0};
  const CameraGlance& g = *std::prev(next);
  const double tau = t - g.start_s;
  double f = 0;
  const double back = tau - g.turn_s - g.hold_s;  // time into the turn back
  if (tau < g.turn_s)
    f = 0.5 * (1 - std::cos(kPi * tau / g.turn_s));
  else if (back < 0)
    f = 1;
  else if (back < g.turn_s)
    f = 0.5 * (1 + std::cos(kPi * back / g.turn_s));
  return {f * g.yaw_rad, f * g.pitch_rad};
}

// Four sides and the top of a box of the given size standing on the body origin (x forward).
std::vector<SceneQuad> BodyBox(double length, double width, double height, double texels_per_m, float brightness) {
  const Eigen::Vector3d lo(-0.5 * length, -0.5 * width, 0);
  const Eigen::Vector3d X(length, 0, 0), Y(0, width, 0), Z(0, 0, height);
  auto quad = [&](const Eigen::Vector3d& origin, const Eigen::Vector3d& u, const Eigen::Vector3d& v, float light) {
    return MakeQuad(origin, u, v, texels_per_m, brightness * light);
  };
  return {quad(lo, X, Z, 0.9f), quad(lo + Y, X, Z, 1.0f), quad(lo, Y, Z, 0.8f), quad(lo + X, Y, Z, 1.1f),
          quad(lo + Z, X, Y, 1.15f)};
}

// Fraction of the image inside the bounding box of the projections of a mover (its geometry
// scaled by scale) over all (T_world_cam, time) views: an upper bound of the area it covers in
// their union, since each quad projects inside the hull of its near-plane-clipped corners.
double BoundingCoverage(const SceneMover& mover, double scale,
                        const std::vector<std::pair<Eigen::Isometry3d, double>>& views, const PinholeCamera& cam) {
  double u_min = std::numeric_limits<double>::infinity(), u_max = -u_min, v_min = u_min, v_max = -u_min;
  auto extend = [&](const Eigen::Vector3d& p) {
    const Eigen::Vector2d uv = cam.Project(p);
    const double u = uv.x(), v = uv.y();
    u_min = std::min(u_min, u);
    u_max = std::max(u_max, u);
    v_min = std::min(v_min, v);
    v_max = std::max(v_max, v);
  };
  for (const auto& [T_world_cam, t] : views) {
    if (!mover.active(t)) continue;
    const Eigen::Isometry3d T_cam_body = T_world_cam.inverse() * mover.PoseAt(t);
    for (const SceneQuad& q : mover.quads) {
      const Eigen::Vector3d o = T_cam_body * (scale * q.origin);
      const Eigen::Vector3d a = T_cam_body.linear() * (scale * q.size_u * q.axis_u);
      const Eigen::Vector3d b = T_cam_body.linear() * (scale * q.size_v * q.axis_v);
      const std::array<Eigen::Vector3d, 4> corners = {o, o + a, o + a + b, o + b};
      for (int k = 0; k < 4; ++k) {
        const Eigen::Vector3d& p = corners[k];
        const Eigen::Vector3d& n = corners[(k + 1) % 4];
        const bool p_in = p.z() >= kNearPlane, n_in = n.z() >= kNearPlane;
        if (p_in) extend(p);
        if (p_in != n_in) extend(p + (n - p) * ((kNearPlane - p.z()) / (n.z() - p.z())));
      }
    }
  }
  const double w = std::min<double>(u_max, cam.width) - std::max(u_min, 0.0);
  const double h = std::min<double>(v_max, cam.height) - std::max(v_min, 0.0);
  if (!(w > 0 && h > 0)) return 0.0;
  return w * h / (static_cast<double>(cam.width) * cam.height);
}

// One pixel of FinishImage: gain, noise drawn from *rng, rounding to a grey level.
[[gnu::always_inline]] inline uint8_t FinishPixel(float x, float gain, float sigma, uint64_t* rng) {
  if (gain != 1.0f) x *= gain;
  if (sigma > 0) x += sigma * GaussFromBits(SplitMix(rng));
  return static_cast<uint8_t>(std::clamp(x + 0.5f, 0.0f, 255.0f));
}

#if defined(__x86_64__) || defined(__i386__)
// The low 64 bits of a * b per lane (AVX2 has only 32 x 32 -> 64-bit products).
__attribute__((target("avx2"))) inline __m256i MulLo64Avx2(__m256i a, __m256i b_lo, __m256i b_hi) {
  const __m256i lo = _mm256_mul_epu32(a, b_lo);
  const __m256i cross = _mm256_add_epi64(_mm256_mul_epu32(_mm256_srli_epi64(a, 32), b_lo), _mm256_mul_epu32(a, b_hi));
  return _mm256_add_epi64(lo, _mm256_slli_epi64(cross, 32));
}

// SplitMix's output for the four states of z, lane by lane.
__attribute__((target("avx2"))) inline __m256i SplitMixOutputAvx2(__m256i z) {
  const __m256i m1_lo = _mm256_set1_epi64x(static_cast<long long>(kSplitMixMul1 & 0xffffffffull));
  const __m256i m1_hi = _mm256_set1_epi64x(static_cast<long long>(kSplitMixMul1 >> 32));
  const __m256i m2_lo = _mm256_set1_epi64x(static_cast<long long>(kSplitMixMul2 & 0xffffffffull));
  const __m256i m2_hi = _mm256_set1_epi64x(static_cast<long long>(kSplitMixMul2 >> 32));
  z = MulLo64Avx2(_mm256_xor_si256(z, _mm256_srli_epi64(z, 30)), m1_lo, m1_hi);
  z = MulLo64Avx2(_mm256_xor_si256(z, _mm256_srli_epi64(z, 27)), m2_lo, m2_hi);
  return _mm256_xor_si256(z, _mm256_srli_epi64(z, 31));
}

// FinishImage's row, eight pixels at a time: the same draws in the same order (pixel k of a group
// takes the state k + 1 steps on) and the same float operations, so the same bits as FinishPixel.
// Returns how many pixels it finished (a multiple of 8); *rng is advanced past them.
__attribute__((target("avx2"))) int FinishRowAvx2(const float* in, int width, float gain, float sigma, uint64_t* rng,
                                                  uint8_t* out) {
  auto steps = [](uint64_t k) { return static_cast<long long>(k * kSplitMixStep); };
  const __m256i steps_a = _mm256_setr_epi64x(steps(1), steps(2), steps(3), steps(4));
  const __m256i steps_b = _mm256_setr_epi64x(steps(5), steps(6), steps(7), steps(8));
  const __m256i low_bytes = _mm256_set1_epi64x(0xffffffffll);
  const __m256i order = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
  const __m256 gain_v = _mm256_set1_ps(gain), sigma_v = _mm256_set1_ps(sigma);
  const __m256 offset = _mm256_set1_ps(510.0f), scale = _mm256_set1_ps(1.0f / 147.8f);
  const __m256 half = _mm256_set1_ps(0.5f), zero = _mm256_setzero_ps(), top = _mm256_set1_ps(255.0f);
  uint64_t state = *rng;
  int u = 0;
  for (; u + 8 <= width; u += 8) {
    __m256 x = _mm256_loadu_ps(in + u);
    if (gain != 1.0f) x = _mm256_mul_ps(x, gain_v);
    if (sigma > 0) {
      const __m256i base = _mm256_set1_epi64x(static_cast<long long>(state));
      // GaussFromBits: the sum of each output's four low bytes (in the low 16 bits of its lane).
      const __m256i a = _mm256_sad_epu8(
          _mm256_and_si256(SplitMixOutputAvx2(_mm256_add_epi64(base, steps_a)), low_bytes), _mm256_setzero_si256());
      const __m256i b = _mm256_sad_epu8(
          _mm256_and_si256(SplitMixOutputAvx2(_mm256_add_epi64(base, steps_b)), low_bytes), _mm256_setzero_si256());
      // Pixels 0-3 from a, 4-7 from b: interleave their low words, then put them in order.
      const __m256i sums =
          _mm256_permutevar8x32_epi32(_mm256_blend_epi32(a, _mm256_slli_epi64(b, 32), 0b10101010), order);
      const __m256 gauss = _mm256_mul_ps(_mm256_sub_ps(_mm256_cvtepi32_ps(sums), offset), scale);
      x = _mm256_add_ps(x, _mm256_mul_ps(sigma_v, gauss));
      state += 8 * kSplitMixStep;
    }
    const __m256i level = _mm256_cvttps_epi32(_mm256_min_ps(_mm256_max_ps(_mm256_add_ps(x, half), zero), top));
    const __m128i words = _mm_packus_epi32(_mm256_castsi256_si128(level), _mm256_extracti128_si256(level, 1));
    _mm_storel_epi64(reinterpret_cast<__m128i*>(out + u), _mm_packus_epi16(words, words));
  }
  *rng = state;
  return u;
}
#endif  // x86

// Gain, noise and rounding: the last step of every image. The noise draws follow the pixels in
// row-major order, so an image depends only on its seed (with or without AVX2).
void FinishImage(const float* value, int width, int height, float gain, float sigma, uint64_t noise_seed,
                 bool use_avx2, cv::Mat* gray) {
  gray->create(height, width, CV_8UC1);
  static const bool cpu_avx2 = HasAvx2();
  [[maybe_unused]] const bool avx2 = use_avx2 && cpu_avx2;
  uint64_t rng = noise_seed;
  for (int v = 0; v < height; ++v) {
    uint8_t* out = gray->ptr<uint8_t>(v);
    const float* in = value + static_cast<size_t>(v) * width;
    int u = 0;
#if defined(__x86_64__) || defined(__i386__)
    if (avx2) u = FinishRowAvx2(in, width, gain, sigma, &rng, out);
#endif
    for (; u < width; ++u) out[u] = FinishPixel(in[u], gain, sigma, &rng);
  }
}

}  // namespace

Eigen::Isometry3d SceneMover::PoseAt(double t) const {
  FLATSLAM_CHECK(!keys.empty(), "scene mover without keys");
  if (period_s > 0) {
    t = keys.front().t_s + std::fmod(t - keys.front().t_s, period_s);
    if (t < keys.front().t_s) t += period_s;
  }
  const auto next =
      std::upper_bound(keys.begin(), keys.end(), t, [](double time, const MoverKey& key) { return time < key.t_s; });
  MoverKey a = keys.front(), b = keys.front();
  if (next == keys.end()) {
    a = b = keys.back();
    if (period_s > 0) b = {keys.front().t_s + period_s, keys.front().position, keys.front().yaw_rad};
  } else if (next != keys.begin()) {
    a = *std::prev(next);
    b = *next;
  }
  const double f = b.t_s > a.t_s ? std::clamp((t - a.t_s) / (b.t_s - a.t_s), 0.0, 1.0) : 0.0;
  const double yaw = a.yaw_rad + f * std::remainder(b.yaw_rad - a.yaw_rad, 2 * kPi);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  T.translation() = a.position + f * (b.position - a.position);
  return T;
}

bool SyntheticOptions::Check() const {
  return (width == 0 || width >= 32) && (height == 0 || height >= 32) && fx >= 0 && fy >= 0 && frame_rate_hz >= 0 &&
         duration_s >= 0 && baseline_m >= 0 && pixel_noise_sigma >= 0 && depth_noise_k >= 0 && max_depth_m > 0 &&
         agent >= 0 && dynamic_fraction >= 0 && dynamic_fraction <= 0.3 && std::abs(rig_error_px) <= 5 &&
         lens_k1 >= 0 && lens_k1 <= 0.1;
}

void ParseSyntheticSpec(const std::string& spec, std::string* scene, SyntheticOptions* options) {
  const size_t colon = spec.find(':');
  *scene = spec.substr(0, colon);
  if (colon == std::string::npos) return;
  std::stringstream list(spec.substr(colon + 1));
  std::string item;
  while (std::getline(list, item, ',')) {
    const size_t eq = item.find('=');
    FLATSLAM_CHECK(eq != std::string::npos, "synthetic spec '", spec, "': expected key=value, got '", item, "'");
    const std::string key = item.substr(0, eq), value = item.substr(eq + 1);
    double v = 0;
    if (key != "sensor") {
      try {
        size_t used = 0;
        v = std::stod(value, &used);
        if (used != value.size()) throw std::invalid_argument(value);
      } catch (const std::exception&) {
        Fail("synthetic spec '", spec, "': ", key, "='", value, "' is not a number");
      }
    }
    if (key == "width")
      options->width = static_cast<int>(v);
    else if (key == "height")
      options->height = static_cast<int>(v);
    else if (key == "fx")
      options->fx = v;
    else if (key == "fps")
      options->frame_rate_hz = v;
    else if (key == "duration")
      options->duration_s = v;
    else if (key == "baseline")
      options->baseline_m = v;
    else if (key == "noise")
      options->pixel_noise_sigma = v;
    else if (key == "depth_noise")
      options->depth_noise_k = v;
    else if (key == "agent")
      options->agent = static_cast<int>(v);
    else if (key == "seed")
      options->seed = static_cast<uint64_t>(v);
    else if (key == "sensor")
      options->sensor = ParseSensor(value);
    else if (key == "dynamic") {
      FLATSLAM_CHECK(v >= 0 && v <= 0.3, "synthetic spec '", spec, "': dynamic=", value,
                     " is outside [0, 0.3] (the largest fraction of the image a moving object covers)");
      options->dynamic_fraction = v;
    } else if (key == "rig_error") {
      FLATSLAM_CHECK(std::abs(v) <= 5, "synthetic spec '", spec, "': rig_error=", value,
                     " is outside [-5, 5] (pixels of disparity)");
      options->rig_error_px = v;
    } else if (key == "k1") {
      FLATSLAM_CHECK(v >= 0 && v <= 0.1, "synthetic spec '", spec, "': k1=", value,
                     " is outside [0, 0.1] (a radial distortion the calibration leaves out)");
      options->lens_k1 = v;
    } else if (key == "structured_light") {
      FLATSLAM_CHECK(v == 0 || v == 1, "synthetic spec '", spec, "': structured_light=", value, " is not 0 or 1");
      options->structured_light = v == 1;
    } else {
      Fail("synthetic spec '", spec, "': unknown key '", key,
           "' (known: width, height, fx, fps, duration, baseline, noise, depth_noise, agent, seed, sensor, "
           "dynamic, rig_error, structured_light, k1)");
    }
  }
}

SyntheticScene::SyntheticScene(SceneDescription description, const SyntheticOptions& options)
    : description_(std::move(description)), options_(options) {
  FLATSLAM_CHECK(options_.Check(), "synthetic options out of range (scene '", description_.name, "')");
  FLATSLAM_CHECK(options_.agent < static_cast<int>(description_.agents.size()), "scene '", description_.name, "' has ",
                 description_.agents.size(), " agent(s); agent ", options_.agent, " does not exist");
  for (size_t m = 0; m < description_.movers.size(); ++m)
    FLATSLAM_CHECK(!description_.movers[m].keys.empty(), "scene '", description_.name, "': mover ", m, " has no keys");
  const int scene_width = description_.default_width > 0 ? description_.default_width : 640;
  if (options_.width == 0) options_.width = scene_width;
  if (options_.height == 0) options_.height = description_.default_height > 0 ? description_.default_height : 480;
  if (options_.fx == 0) {
    options_.fx =
        description_.default_fx > 0 ? description_.default_fx * options_.width / scene_width : 0.75 * options_.width;
  }
  if (options_.fy == 0) options_.fy = options_.fx;
  if (options_.frame_rate_hz == 0)
    options_.frame_rate_hz = description_.default_frame_rate_hz > 0 ? description_.default_frame_rate_hz : 20;
  if (options_.duration_s == 0) options_.duration_s = description_.default_duration_s;
  if (options_.baseline_m == 0) options_.baseline_m = description_.default_baseline_m;

  calibration_.sensor = options_.sensor;
  calibration_.camera =
      PinholeCamera{options_.fx,    options_.fy,    (options_.width - 1) * 0.5, (options_.height - 1) * 0.5,
                    options_.width, options_.height};
  calibration_.baseline_m = options_.sensor == Sensor::kStereo ? options_.baseline_m : 0.0;
  calibration_.frame_rate_hz = options_.frame_rate_hz;
  frame_count_ = static_cast<size_t>(std::llround(options_.duration_s * options_.frame_rate_hz));
  FLATSLAM_CHECK(frame_count_ > 0, "synthetic scene '", description_.name, "' has no frames");
  if (options_.lens_k1 > 0) {
    // Each pixel of the distorted image shows the undistorted view at radius r_u, where
    // r_u (1 + k1 r_u^2) is its own radius r_d (Newton's method from r_d; with k1 >= 0 r_u <= r_d).
    const PinholeCamera& c = calibration_.camera;
    lens_map_x_.create(options_.height, options_.width, CV_32F);
    lens_map_y_.create(options_.height, options_.width, CV_32F);
    for (int v = 0; v < options_.height; ++v)
      for (int u = 0; u < options_.width; ++u) {
        const double xd = (u - c.cx) / c.fx, yd = (v - c.cy) / c.fy, rd = std::hypot(xd, yd);
        double r = rd;
        for (int k = 0; k < 20; ++k) r -= (r + options_.lens_k1 * r * r * r - rd) / (1 + 3 * options_.lens_k1 * r * r);
        const double f = rd > 0 ? r / rd : 1.0;
        lens_map_x_.at<float>(v, u) = static_cast<float>(c.cx + c.fx * xd * f);
        lens_map_y_.at<float>(v, u) = static_cast<float>(c.cy + c.fy * yd * f);
      }
  }

  path_ = std::make_unique<PathTable>(description_.agents[options_.agent].control_points);

  const SceneExposure& exposure = description_.exposure;
  if (exposure.gain_step_every_s > 0) {
    // Auto-exposure steps up or down, drifting back towards unit gain.
    std::mt19937_64 rng(description_.world_seed * 0x2545f4914f6cdd1dull + 7);
    std::uniform_real_distribution<double> interval(0.5 * exposure.gain_step_every_s, 1.5 * exposure.gain_step_every_s);
    std::uniform_real_distribution<double> size(exposure.gain_step_min, exposure.gain_step_max), unit(0.0, 1.0);
    const double end = static_cast<double>(frame_count_) / options_.frame_rate_hz + exposure.exposure_s;
    double gain = 1;
    for (double t = interval(rng); t < end; t += interval(rng)) {
      const double step = size(rng);
      const bool up = unit(rng) < (gain < 0.85 ? 1.0 : gain > 1.15 ? 0.0 : 0.5);
      gain *= up ? 1 + step : 1 - step;
      gain_steps_.emplace_back(t, gain);
    }
  }

  if (options_.dynamic_fraction > 0) AddDynamicObjects();

  // Static quads first (their texture seeds do not depend on the movers), then mover quads.
  std::vector<const SceneQuad*> quads;
  for (const SceneQuad& q : description_.quads) quads.push_back(&q);
  for (const SceneMover& mover : description_.movers) {
    mover_texture_.push_back(quads.size());
    for (const SceneQuad& q : mover.quads) quads.push_back(&q);
  }
  for (const SceneQuad* q : quads) {
    const Eigen::Vector3d half = 0.5 * (q->size_u * q->axis_u + q->size_v * q->axis_v);
    bounds_.emplace_back(q->origin.x() + half.x(), q->origin.y() + half.y(), q->origin.z() + half.z(), half.norm());
  }
  textures_.resize(quads.size());
  tbb::parallel_for(size_t{0}, quads.size(), [&](size_t i) {
    const SceneQuad& q = *quads[i];
    auto tex = std::make_unique<Texture>();
    const double longest = std::max(q.size_u, q.size_v);
    tex->texels_per_m = static_cast<float>(std::min(q.texels_per_m, kMaxTextureSide / longest));
    const int w = std::max(4, static_cast<int>(std::ceil(q.size_u * tex->texels_per_m)));
    const int h = std::max(4, static_cast<int>(std::ceil(q.size_v * tex->texels_per_m)));
    tex->images.push_back(GenerateTexture(q.style, w, h, tex->texels_per_m, description_.world_seed * 1000003ull + i));
    while (tex->images.back().cols > 8 && tex->images.back().rows > 8) {
      cv::Mat down;
      cv::pyrDown(tex->images.back(), down);
      tex->images.push_back(down);
    }
    for (cv::Mat& m : tex->images) {  // a padding row after each level (see TextureLevel)
      cv::Mat padded(m.rows + 1, m.cols, CV_8UC1, cv::Scalar(0));
      m.copyTo(padded.rowRange(0, m.rows));
      m = padded.rowRange(0, m.rows);
    }
    for (size_t l = 0; l < tex->images.size(); ++l) {
      const cv::Mat& m = tex->images[l];
      tex->levels.push_back({m.ptr<uint8_t>(0), m.cols, m.rows, m.step[0], 1.0f / static_cast<float>(1u << l)});
    }
    tex->footprint_scale2 = std::pow(tex->texels_per_m / static_cast<float>(calibration_.camera.fx), 2.0f);
    tex->last_level = static_cast<float>(tex->levels.size()) - 1.001f;
    tex->brightness = q.brightness;
    tex->size_u = static_cast<float>(q.size_u);
    tex->size_v = static_cast<float>(q.size_v);
    textures_[i] = std::move(tex);
  });
}

SyntheticScene::~SyntheticScene() = default;

void SyntheticScene::AddDynamicObjects() {
  const CameraPath& agent = description_.agents[options_.agent];
  double camera_height = 0;
  for (const Eigen::Vector3d& p : agent.control_points) camera_height += p.z();
  camera_height /= static_cast<double>(agent.control_points.size());
  const double d = description_.dynamic_distance_m > 0 ? description_.dynamic_distance_m : 2 * camera_height;
  const double speed = agent.speed_mps;
  // Crossing in front only where the camera needs half a second or more to reach the crossing.
  const bool crossers = d >= 0.5 * speed;
  const double end = static_cast<double>(frame_count_ - 1) / options_.frame_rate_hz;
  const double half_view = 0.5 * options_.width / options_.fx;  // tangent of half the field of view
  const double texels_per_m = std::clamp(2 * options_.fx / d, 16.0, 256.0);
  std::mt19937_64 rng(description_.world_seed * 0x9e3779b97f4a7c15ull + 977 * (options_.agent + 1));
  std::uniform_real_distribution<double> unit(0.0, 1.0);

  double t0 = std::min(1.0, 0.1 * end);
  for (int k = 0; end - t0 >= 1.0; ++k) {
    const double window = std::min(4.0 + 3.0 * unit(rng), end - t0), t1 = t0 + window;
    SceneMover mover;
    mover.active_from_s = t0;
    mover.active_until_s = t1;
    const float brightness = static_cast<float>(0.75 + 0.35 * unit(rng));
    if (crossers && k % 2 == 0) {
      // Crosses the camera's view direction at distance d, at constant speed, mid-window.
      const Eigen::Isometry3d C = PoseAt(0.5 * (t0 + t1));
      Eigen::Vector3d forward = C.linear().col(2);
      forward.z() = 0;
      forward.normalize();
      const Eigen::Vector3d side(-forward.y(), forward.x(), 0);
      Eigen::Vector3d centre = C.translation() + d * forward;
      centre.z() = 0;
      const double reach = 1.2 * (d + 0.5 * speed * window) * half_view + d;  // starts out of view
      const double dir = unit(rng) < 0.5 ? 1.0 : -1.0;
      const double yaw = std::atan2(dir * side.y(), dir * side.x());
      mover.keys = {{t0, centre - dir * reach * side, yaw}, {t1, centre + dir * reach * side, yaw}};
      mover.quads = BodyBox(0.6 * d, 0.35 * d, 0.5 * d, texels_per_m, brightness);
    } else {
      // Moves along the camera's path beside it: from behind to ahead (overtaking) or back.
      const double lateral = (unit(rng) < 0.5 ? 1.0 : -1.0) * 0.75 * d;
      const double behind = -1.5 * d, ahead = 6 * d;
      const bool overtaking = unit(rng) < 0.7;
      const double gap_rate = (overtaking ? ahead - behind : behind - ahead) / window;
      for (double t = t0;; t = std::min(t + 0.05, t1)) {
        const double gap = (overtaking ? behind : ahead) + gap_rate * (t - t0);
        const double s = agent.start_s + speed * t + gap;
        Eigen::Vector3d tangent = path_->At(s + 0.05) - path_->At(s - 0.05);
        tangent.z() = 0;
        tangent.normalize();
        Eigen::Vector3d p = path_->At(s) + lateral * Eigen::Vector3d(-tangent.y(), tangent.x(), 0);
        p.z() = 0;
        const double yaw = std::atan2(tangent.y(), tangent.x()) + (speed + gap_rate < 0 ? kPi : 0.0);
        mover.keys.push_back({t, p, yaw});
        if (t >= t1) break;
      }
      mover.quads = BodyBox(1.0 * d, 0.45 * d, 0.45 * d, texels_per_m, brightness);
    }

    // Size the object so that, over every rendered instant of its window, the bounding box of
    // its projection covers at most the target fraction of either view.
    std::vector<std::vector<std::pair<Eigen::Isometry3d, double>>> views;
    const size_t first = static_cast<size_t>(std::max(0.0, std::ceil(t0 * options_.frame_rate_hz)));
    for (size_t i = first; i < frame_count_; ++i) {
      const double t = static_cast<double>(timestamp_ns(i)) * 1e-9;
      if (t > t1) break;
      std::vector<std::pair<Eigen::Isometry3d, double>> left, right;
      for (double tau : ExposureTimes(t)) {
        const Eigen::Isometry3d T = PoseAt(tau);
        left.emplace_back(T, tau);
        if (options_.sensor == Sensor::kStereo)
          right.emplace_back(T * Eigen::Translation3d(options_.baseline_m, 0, 0), tau);
      }
      views.push_back(std::move(left));
      if (!right.empty()) views.push_back(std::move(right));
    }
    auto coverage = [&](double scale) {
      double worst = 0;
      for (const auto& group : views)
        worst = std::max(worst, BoundingCoverage(mover, scale, group, calibration_.camera));
      return worst;
    };
    const double target = options_.dynamic_fraction * (k == 0 ? 1.0 : 0.5 + 0.5 * unit(rng));
    double lo = 0, hi = 1;
    while (coverage(hi) <= target && hi < 8) hi *= 2;
    if (coverage(hi) <= target) {
      lo = 1;  // never large in view: natural size
    } else {
      for (int iteration = 0; iteration < 30; ++iteration) {
        const double mid = 0.5 * (lo + hi);
        (coverage(mid) <= target ? lo : hi) = mid;
      }
    }
    for (SceneQuad& q : mover.quads) {
      q.origin *= lo;
      q.size_u *= lo;
      q.size_v *= lo;
    }
    description_.movers.push_back(std::move(mover));
    t0 = t1 + 1.0 + 2.0 * unit(rng);
  }
}

int64_t SyntheticScene::timestamp_ns(size_t frame) const {
  return static_cast<int64_t>(std::llround(static_cast<double>(frame) * 1e9 / options_.frame_rate_hz));
}

double SyntheticScene::path_length_m() const {
  return description_.agents[options_.agent].speed_mps * (frame_count_ - 1) / options_.frame_rate_hz;
}

double SyntheticScene::loop_length_m() const {
  return path_->length;
}

Eigen::Isometry3d SyntheticScene::PoseAt(double t) const {
  const CameraPath& agent = description_.agents[options_.agent];
  const double s = agent.start_s + agent.speed_mps * t;
  Eigen::Vector3d position = path_->At(s);
  position.z() += agent.height_wobble_m * std::sin(2 * kPi * t / 4.1);
  Eigen::Vector3d tangent = path_->At(s + 0.05) - path_->At(s - 0.05);
  tangent.z() = 0;
  tangent.normalize();
  double yaw = agent.yaw_wobble_rad * std::sin(2 * kPi * t / 7.3);
  double pitch = agent.pitch_wobble_rad * std::sin(2 * kPi * t / 5.1);
  if (!agent.glances.empty()) {
    const auto [glance_yaw, glance_pitch] = GlanceOffset(agent.glances, t);
    yaw += glance_yaw;
    pitch += glance_pitch;
  }
  const Eigen::Vector3d up = Eigen::Vector3d::UnitZ();
  Eigen::Vector3d forward = Eigen::AngleAxisd(yaw, up) * tangent;
  forward = (std::cos(pitch) * forward + std::sin(pitch) * up).normalized();
  Eigen::Vector3d right = forward.cross(up).normalized();
  if (agent.roll_wobble_rad != 0) {
    const double roll = agent.roll_wobble_rad * std::sin(2 * kPi * t / 6.3);
    right = std::cos(roll) * right + std::sin(roll) * forward.cross(right);
  }
  const Eigen::Vector3d down = forward.cross(right);
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear().col(0) = right;
  T.linear().col(1) = down;
  T.linear().col(2) = forward;
  T.translation() = position;
  return T;
}

double SyntheticScene::GainAt(double t) const {
  const SceneExposure& exposure = description_.exposure;
  double gain = 1;
  if (exposure.gain_wobble > 0)
    gain *= 1 + exposure.gain_wobble * (0.6 * std::sin(2 * kPi * t / 9.7) + 0.4 * std::sin(2 * kPi * t / 3.1 + 1.3));
  const auto next =
      std::upper_bound(gain_steps_.begin(), gain_steps_.end(), t,
                       [](double time, const std::pair<double, double>& step) { return time < step.first; });
  if (next != gain_steps_.begin()) gain *= std::prev(next)->second;
  return gain;
}

std::vector<double> SyntheticScene::ExposureTimes(double t) const {
  const double exposure = description_.exposure.exposure_s;
  if (exposure <= 0) return {t};
  // Image motion over the exposure: rotation at the focal length plus translation seen at 1 m.
  // Below 1.5 px the image stays sharp; above, sub-frames at most 1.5 px apart, an odd count so
  // that the middle one is at the frame time.
  const Eigen::Isometry3d a = PoseAt(t - 0.5 * exposure), b = PoseAt(t + 0.5 * exposure);
  const double angle = Eigen::AngleAxisd(a.linear().transpose() * b.linear()).angle();
  const double pixels = options_.fx * (angle + (b.translation() - a.translation()).norm() / 1.0);
  if (pixels <= 1.5) return {t};
  const int n = 1 + 2 * std::min(7, static_cast<int>(std::ceil(pixels / 3.0)));
  std::vector<double> times(n);
  for (int k = 0; k < n; ++k) times[k] = t + exposure * (static_cast<double>(k) / (n - 1) - 0.5);
  return times;
}

void SyntheticScene::RenderLinear(const Eigen::Isometry3d& T_world_cam, double t_s, float* value,
                                  cv::Mat* depth_m) const {
  const int W = options_.width, H = options_.height;
  const float fx = static_cast<float>(calibration_.camera.fx), fy = static_cast<float>(calibration_.camera.fy);
  const float cx = static_cast<float>(calibration_.camera.cx), cy = static_cast<float>(calibration_.camera.cy);
  thread_local RenderScratch scratch;
  scratch.Resize(static_cast<size_t>(W) * H);

  const Eigen::Matrix3d R_cam_world = T_world_cam.linear().transpose();
  const Eigen::Vector3d t_cam_world = -R_cam_world * T_world_cam.translation();
  const float inv_fx = 1.0f / fx, inv_fy = 1.0f / fy;
  // Camera-frame normal of every quad drawn in this view (the shading pass reads only those).
  thread_local std::vector<Eigen::Vector3f> normals;
  normals.resize(textures_.size());

  // Rasterizes the world-frame quad origin + s axis_u + t axis_v whose texture is textures_[qi]
  // into the z-buffer, keeping per pixel the nearest quad and its (s, t).
  auto raster = [&](const Eigen::Vector3d& origin, const Eigen::Vector3d& axis_u, const Eigen::Vector3d& axis_v,
                    double quad_size_u, double quad_size_v, size_t qi) {
    const Eigen::Vector3d o = R_cam_world * origin + t_cam_world;
    const Eigen::Vector3d a = R_cam_world * axis_u;
    const Eigen::Vector3d b = R_cam_world * axis_v;
    // Clip the quad against the near plane, then bound its projection.
    const std::array<Eigen::Vector3d, 4> corners = {o, o + quad_size_u * a, o + quad_size_u * a + quad_size_v * b,
                                                    o + quad_size_v * b};
    double u_min = W, u_max = -1, v_min = H, v_max = -1;
    bool any = false;
    auto extend = [&](const Eigen::Vector3d& p) {
      const double u = fx * p.x() / p.z() + cx, v = fy * p.y() / p.z() + cy;
      u_min = std::min(u_min, u);
      u_max = std::max(u_max, u);
      v_min = std::min(v_min, v);
      v_max = std::max(v_max, v);
      any = true;
    };
    for (int k = 0; k < 4; ++k) {
      const Eigen::Vector3d& p = corners[k];
      const Eigen::Vector3d& q = corners[(k + 1) % 4];
      const bool p_in = p.z() >= kNearPlane, q_in = q.z() >= kNearPlane;
      if (p_in) extend(p);
      if (p_in != q_in) extend(p + (q - p) * ((kNearPlane - p.z()) / (q.z() - p.z())));
    }
    if (!any) return;
    const int u0 = std::max(0, static_cast<int>(std::floor(u_min)) - 1);
    const int u1 = std::min(W - 1, static_cast<int>(std::ceil(u_max)) + 1);
    const int v0 = std::max(0, static_cast<int>(std::floor(v_min)) - 1);
    const int v1 = std::min(H - 1, static_cast<int>(std::ceil(v_max)) + 1);
    if (u0 > u1 || v0 > v1) return;

    // Plane homography: camera point X = [a b o] (s, t, 1)^T; M maps a ray to (s, t, 1) / z.
    Eigen::Matrix3d Hm;
    Hm << a, b, o;
    if (std::abs(Hm.determinant()) < 1e-9) return;  // plane through the optical centre
    const Eigen::Matrix3f M = Hm.inverse().cast<float>();
    normals[qi] = a.cross(b).normalized().cast<float>();
    // Along a row, q(u) = q_row + u * du is linear, and the quad is exactly where
    // q.z > 0, 0 <= q.x <= size_u q.z and 0 <= q.y <= size_v q.z: five half-lines in u.
    const Eigen::Vector3d du = M.col(0).cast<double>() / fx;
    for (int v = v0; v <= v1; ++v) {
      const Eigen::Vector3d q_row =
          M.col(0).cast<double>() * (-cx / fx) + M.col(1).cast<double>() * ((v - cy) / fy) + M.col(2).cast<double>();
      double lo = u0, hi = u1;
      auto keep = [&](double c0, double c1) {  // c0 + c1 u >= 0
        if (c1 > 0)
          lo = std::max(lo, -c0 / c1);
        else if (c1 < 0)
          hi = std::min(hi, -c0 / c1);
        else if (c0 < 0)
          hi = -1;
      };
      keep(q_row.z(), du.z());
      keep(q_row.x(), du.x());
      keep(quad_size_u * q_row.z() - q_row.x(), quad_size_u * du.z() - du.x());
      keep(q_row.y(), du.y());
      keep(quad_size_v * q_row.z() - q_row.y(), quad_size_v * du.z() - du.y());
      if (!(lo <= hi)) continue;  // empty (lo, hi stay within [u0, u1] otherwise)
      const int ua = static_cast<int>(std::ceil(lo)), ub = static_cast<int>(std::floor(hi));
      if (ua > ub) continue;
      Eigen::Vector3f q = (q_row + du * ua).cast<float>();
      const Eigen::Vector3f duf = du.cast<float>();
      const size_t row = static_cast<size_t>(v) * W;
      for (int u = ua; u <= ub; ++u, q += duf) {
        const float w = q.z();
        const size_t p = row + u;
        if (w <= scratch.inv_depth[p]) continue;
        scratch.inv_depth[p] = w;
        scratch.quad[p] = static_cast<int32_t>(qi);
        scratch.s[p] = q.x();
        scratch.t[p] = q.y();
      }
    }
  };
  // Quads whose bounding sphere lies behind the near plane or outside a side of the view
  // (widened by 2 px) could not cover any pixel centre: skipped before any further work.
  const double tan_x = (std::max<double>(cx, W - 1 - cx) + 2) / fx, tan_y = (std::max<double>(cy, H - 1 - cy) + 2) / fy;
  const double norm_x = std::sqrt(1 + tan_x * tan_x), norm_y = std::sqrt(1 + tan_y * tan_y);
  auto outside = [&](const Eigen::Vector3d& c, double r) {
    return c.z() + r < kNearPlane || (tan_x * c.z() - std::abs(c.x())) < -r * norm_x ||
           (tan_y * c.z() - std::abs(c.y())) < -r * norm_y;
  };
  for (size_t qi = 0; qi < description_.quads.size(); ++qi) {
    if (outside(R_cam_world * bounds_[qi].head<3>() + t_cam_world, bounds_[qi].w())) continue;
    const SceneQuad& quad = description_.quads[qi];
    raster(quad.origin, quad.axis_u, quad.axis_v, quad.size_u, quad.size_v, qi);
  }
  for (size_t m = 0; m < description_.movers.size(); ++m) {
    const SceneMover& mover = description_.movers[m];
    if (!mover.active(t_s)) continue;
    const Eigen::Isometry3d T_world_body = mover.PoseAt(t_s);
    for (size_t j = 0; j < mover.quads.size(); ++j) {
      const size_t qi = mover_texture_[m] + j;
      if (outside(R_cam_world * (T_world_body * bounds_[qi].head<3>()) + t_cam_world, bounds_[qi].w())) continue;
      const SceneQuad& quad = mover.quads[j];
      raster(T_world_body * quad.origin, T_world_body.linear() * quad.axis_u, T_world_body.linear() * quad.axis_v,
             quad.size_u, quad.size_v, qi);
    }
  }

  if (depth_m) depth_m->create(H, W, CV_32FC1);
  static const bool cpu_avx2 = HasAvx2();
  [[maybe_unused]] const bool avx2 = options_.use_avx2 && cpu_avx2;
  for (int v = 0; v < H; ++v) {
    float* out = value + static_cast<size_t>(v) * W;
    float* dout = depth_m ? depth_m->ptr<float>(v) : nullptr;
    const size_t row = static_cast<size_t>(v) * W;
    const float ry = (v - cy) * inv_fy;
    auto shade = [&](int u) {
      const size_t p = row + u;
      const int32_t qi = scratch.quad[p];
      if (qi < 0) {
        out[u] = 150.0f + 60.0f * static_cast<float>(v) / H;  // featureless sky / void
        if (dout) dout[u] = 0.0f;
        return;
      }
      const float w = scratch.inv_depth[p];
      const Eigen::Vector3f& normal = normals[qi];
      const Texture& tex = *textures_[qi];
      // Squared texel footprint of one pixel, widened on slanted surfaces (cosine floor
      // 0.2), picks the mip level: footprint^2 = (tpm/fx)^2 |ray|^2 / (w^2 max(cos^2 |ray|^2)).
      const float rx = (u - cx) * inv_fx;
      const float ray2 = rx * rx + ry * ry + 1.0f;
      const float dot = normal.x() * rx + normal.y() * ry + normal.z();
      const float footprint2 = tex.footprint_scale2 * ray2 / (w * w * std::max(dot * dot, 0.04f * ray2));
      float level = footprint2 > 1.0f ? 0.5f * FastLog2(footprint2) : 0.0f;
      level = std::min(level, tex.last_level);
      const int l0 = static_cast<int>(level);
      // Blend two levels only around the middle of a level ("brilinear"): fewer samples.
      const float blend = std::clamp((level - l0 - 0.3f) * 2.5f, 0.0f, 1.0f);
      const float inv = 1.0f / w;
      const float s = std::clamp(scratch.s[p] * inv, 0.0f, tex.size_u);
      const float t = std::clamp(scratch.t[p] * inv, 0.0f, tex.size_v);
      const float x0 = s * tex.texels_per_m, y0 = t * tex.texels_per_m;
      const float a = SampleLevel(tex.levels[l0], x0, y0);
      const float b = blend > 0.0f ? SampleLevel(tex.levels[l0 + 1], x0, y0) : a;
      out[u] = (a + blend * (b - a)) * tex.brightness;
      if (dout) dout[u] = 1.0f / w;
    };
    // Runs of pixels on one quad go eight at a time through the vector path where the CPU has
    // AVX2 (the same bits as the scalar one).
    for (int u = 0; u < W;) {
      const int32_t qi = scratch.quad[row + u];
      int end = u + 1;
      while (end < W && scratch.quad[row + end] == qi) ++end;
#if defined(__x86_64__) || defined(__i386__)
      if (qi >= 0 && avx2) {
        const Texture& tex = *textures_[qi];
        const QuadShading quad{tex.levels.data(), tex.footprint_scale2, tex.last_level,   tex.brightness,
                               tex.size_u,        tex.size_v,           tex.texels_per_m, normals[qi].x(),
                               normals[qi].y(),   normals[qi].z()};
        while (u < end) {
          const int count = std::min(8, end - u);
          const size_t p = row + u;
          ShadeAvx2(quad, u, count, ry, cx, inv_fx, &scratch.inv_depth[p], &scratch.s[p], &scratch.t[p], out + u,
                    dout ? dout + u : nullptr);
          u += count;
        }
      }
#endif
      for (; u < end; ++u) shade(u);
    }
  }
}

void SyntheticScene::ApplyLens(float* value, cv::Mat* depth_m) const {
  if (lens_map_x_.empty()) return;
  // The view as the distorted image shows it, before noise (which the sensor adds); depth alike,
  // nearest, so that no depth mixes two surfaces.
  thread_local cv::Mat warped;
  cv::Mat linear(options_.height, options_.width, CV_32F, value);
  cv::remap(linear, warped, lens_map_x_, lens_map_y_, cv::INTER_LINEAR, cv::BORDER_REPLICATE);
  warped.copyTo(linear);
  if (depth_m != nullptr && !depth_m->empty()) {
    cv::Mat depth_warped;
    cv::remap(*depth_m, depth_warped, lens_map_x_, lens_map_y_, cv::INTER_NEAREST, cv::BORDER_REPLICATE);
    *depth_m = depth_warped;
  }
}

void SyntheticScene::RenderView(const Eigen::Isometry3d& T_world_cam, double t_s, uint64_t noise_seed, cv::Mat* gray,
                                cv::Mat* depth_m) const {
  thread_local std::vector<float> value;
  value.resize(static_cast<size_t>(options_.width) * options_.height);
  RenderLinear(T_world_cam, t_s, value.data(), depth_m);
  ApplyLens(value.data(), depth_m);
  const float sigma = noise_seed ? static_cast<float>(options_.pixel_noise_sigma) : 0.0f;
  FinishImage(value.data(), options_.width, options_.height, 1.0f, sigma, noise_seed, options_.use_avx2, gray);
}

void SyntheticScene::RenderExposure(const std::vector<double>& times, double offset_x, float gain, uint64_t noise_seed,
                                    cv::Mat* gray, cv::Mat* depth_m) const {
  const size_t n = static_cast<size_t>(options_.width) * options_.height;
  auto pose = [&](double t) -> Eigen::Isometry3d {
    const Eigen::Isometry3d T_world_cam = PoseAt(t);
    if (offset_x == 0) return T_world_cam;
    // The right camera, turned by the rig error: a point at depth z lands fx * angle pixels left
    // of where the exact rig shows it, so its disparity grows by rig_error_px.
    const double angle = options_.rig_error_px / calibration_.camera.fx;
    return T_world_cam * Eigen::Translation3d(offset_x, 0, 0) * Eigen::AngleAxisd(angle, Eigen::Vector3d::UnitY());
  };
  thread_local std::vector<float> value, sub;
  value.resize(n);
  if (times.size() == 1) {
    RenderLinear(pose(times[0]), times[0], value.data(), depth_m);
  } else {
    // Motion blur: the mean of the sub-frames; depth from the middle one, at the frame time.
    sub.resize(n);
    std::fill(value.begin(), value.end(), 0.0f);
    for (size_t k = 0; k < times.size(); ++k) {
      RenderLinear(pose(times[k]), times[k], sub.data(), k == times.size() / 2 ? depth_m : nullptr);
      for (size_t p = 0; p < n; ++p) value[p] += sub[p];
    }
    const float scale = 1.0f / static_cast<float>(times.size());
    for (float& x : value) x *= scale;
  }
  ApplyLens(value.data(), depth_m);
  const float sigma = noise_seed ? static_cast<float>(options_.pixel_noise_sigma) : 0.0f;
  FinishImage(value.data(), options_.width, options_.height, gain, sigma, noise_seed, options_.use_avx2, gray);
}

Frame SyntheticScene::Render(size_t i) const {
  FLATSLAM_CHECK(i < frame_count_, "synthetic frame ", i, " out of range (", frame_count_, " frames)");
  Frame frame;
  frame.index = i;
  frame.t_ns = timestamp_ns(i);
  // Every view of the frame (both eyes, depth, movers) is rendered at the frame's time.
  const double t = static_cast<double>(frame.t_ns) * 1e-9;
  const std::vector<double> times = ExposureTimes(t);
  const float gain = static_cast<float>(GainAt(t));
  // Noise seeds depend only on (seed, agent, frame, view): any thread order gives the same pixels.
  uint64_t mix = options_.seed * 0x9e3779b97f4a7c15ull + (static_cast<uint64_t>(options_.agent) << 40) + i * 4;
  const uint64_t seed_left = SplitMix(&mix) | 1, seed_right = SplitMix(&mix) | 1, seed_depth = SplitMix(&mix);
  const bool noisy = options_.pixel_noise_sigma > 0;
  if (options_.sensor == Sensor::kRgbd) {
    cv::Mat depth;
    RenderExposure(times, 0.0, gain, noisy ? seed_left : 0, &frame.left, &depth);
    uint64_t rng = seed_depth;
    if (options_.structured_light)
      StructuredLightDepth(calibration_.camera.fx, static_cast<float>(options_.depth_noise_k), &rng, &depth);
    else
      NoisyDepth(static_cast<float>(options_.depth_noise_k), static_cast<float>(options_.max_depth_m), &rng, &depth);
    frame.depth = depth;
  } else {
    RenderExposure(times, 0.0, gain, noisy ? seed_left : 0, &frame.left, nullptr);
    if (options_.sensor == Sensor::kStereo)
      RenderExposure(times, options_.baseline_m, gain, noisy ? seed_right : 0, &frame.right, nullptr);
  }
  return frame;
}

Trajectory SyntheticScene::GroundTruth() const {
  Trajectory gt(frame_count_);
  for (size_t i = 0; i < frame_count_; ++i) {
    gt[i].t_ns = timestamp_ns(i);
    gt[i].T_world_cam = PoseAt(static_cast<double>(gt[i].t_ns) * 1e-9);
  }
  return gt;
}

namespace {

class SyntheticDataset final : public Dataset {
 public:
  SyntheticDataset(SceneDescription scene, const SyntheticOptions& options) : scene_(std::move(scene), options) {}

  std::string name() const override {
    std::ostringstream out;
    out << "synthetic " << scene_.description().name << " (agent " << scene_.options().agent << ", "
        << SensorName(scene_.options().sensor) << ")";
    return out.str();
  }
  const Calibration& calibration() const override { return scene_.calibration(); }
  size_t size() const override { return scene_.frame_count(); }
  Frame read(size_t i) const override { return scene_.Render(i); }
  std::optional<Trajectory> ground_truth() const override { return scene_.GroundTruth(); }

 private:
  SyntheticScene scene_;
};

}  // namespace

std::unique_ptr<Dataset> OpenSyntheticDataset(const std::string& spec, const DatasetOptions& options) {
  std::string scene;
  SyntheticOptions synth;
  synth.seed = options.seed;
  if (options.sensor) synth.sensor = *options.sensor;
  ParseSyntheticSpec(spec, &scene, &synth);
  return std::make_unique<SyntheticDataset>(MakeScene(scene), synth);
}

}  // namespace flatslam
