#include "frontend/stereo_matcher.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <vector>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

#include "core/cpu_features.h"
#include "core/error.h"
#include "core/requirements.h"

namespace flatslam {
namespace {

// Zero-mean SAD of the (2w+1)^2 left patch around (xl, yl) against the right windows centred on
// (xr_begin + k, yl), k in [0, count), all on one pyramid level. With n pixels and patch sums
// S_L, S_R, each pixel adds |n (L - R) - (S_L - S_R)| (= n |(L - mean_L) - (R - mean_R)|, in
// integers), capped at 32767 so that 16-bit lanes hold it; the cap only touches pixels whose
// mean-free difference exceeds 32767 / n grey levels (270 for the default 11 x 11).
void ZeroMeanSadsBaseline(const cv::Mat& limg, int xl, int yl, const cv::Mat& rimg, int xr_begin, int count, int w,
                          int* sads) {
  const int side = 2 * w + 1, n = side * side;
  int left_sum = 0;
  for (int r = 0; r < side; ++r) {
    const uint8_t* row = limg.ptr<uint8_t>(yl - w + r) + xl - w;
    for (int c = 0; c < side; ++c) left_sum += row[c];
  }
  for (int k = 0; k < count; ++k) {
    const int x0 = xr_begin + k - w;
    int right_sum = 0;
    for (int r = 0; r < side; ++r) {
      const uint8_t* row = rimg.ptr<uint8_t>(yl - w + r) + x0;
      for (int c = 0; c < side; ++c) right_sum += row[c];
    }
    const int offset = left_sum - right_sum;
    int sad = 0;
    for (int r = 0; r < side; ++r) {
      const uint8_t* lrow = limg.ptr<uint8_t>(yl - w + r) + xl - w;
      const uint8_t* rrow = rimg.ptr<uint8_t>(yl - w + r) + x0;
      for (int c = 0; c < side; ++c) sad += std::min(std::abs(n * (lrow[c] - rrow[c]) - offset), 32767);
    }
    sads[k] = sad;
  }
}

#if defined(__x86_64__) || defined(__i386__)
// The same sums in 16-bit lanes, one patch row per step. Needs n * 255 < 32768 (2w+1 <= 11) and
// 16 readable bytes from every window's and the patch's left column.
__attribute__((target("avx2"))) void ZeroMeanSadsAvx2(const cv::Mat& limg, int xl, int yl, const cv::Mat& rimg,
                                                      int xr_begin, int count, int w, int* sads) {
  const int side = 2 * w + 1, n = side * side;
  alignas(32) int16_t lane_mask_values[16];
  for (int c = 0; c < 16; ++c) lane_mask_values[c] = c < side ? -1 : 0;
  const __m256i lane_mask = _mm256_load_si256(reinterpret_cast<const __m256i*>(lane_mask_values));
  const __m256i n16 = _mm256_set1_epi16(static_cast<int16_t>(n)), ones = _mm256_set1_epi16(1);
  __m256i left_rows[32];  // n * L per patch row
  int left_sum = 0;
  for (int r = 0; r < side; ++r) {
    const uint8_t* row = limg.ptr<uint8_t>(yl - w + r) + xl - w;
    const __m256i v =
        _mm256_and_si256(_mm256_cvtepu8_epi16(_mm_loadu_si128(reinterpret_cast<const __m128i*>(row))), lane_mask);
    left_rows[r] = _mm256_mullo_epi16(v, n16);
    for (int c = 0; c < side; ++c) left_sum += row[c];
  }
  // Column sums of the right band, then window sums by sliding.
  int column_sum[64 * 2 + 32];
  const int first_column = xr_begin - w, columns = count + 2 * w;
  for (int c = 0; c < columns; ++c) column_sum[c] = 0;
  for (int r = 0; r < side; ++r) {
    const uint8_t* row = rimg.ptr<uint8_t>(yl - w + r) + first_column;
    for (int c = 0; c < columns; ++c) column_sum[c] += row[c];
  }
  int window_sum = 0;
  for (int c = 0; c < side; ++c) window_sum += column_sum[c];
  for (int k = 0; k < count; ++k) {
    if (k > 0) window_sum += column_sum[k + side - 1] - column_sum[k - 1];
    const __m256i offset = _mm256_set1_epi16(static_cast<int16_t>(left_sum - window_sum));
    __m256i acc = _mm256_setzero_si256();
    for (int r = 0; r < side; ++r) {
      const uint8_t* row = rimg.ptr<uint8_t>(yl - w + r) + first_column + k;
      const __m256i v = _mm256_cvtepu8_epi16(_mm_loadu_si128(reinterpret_cast<const __m128i*>(row)));
      // n (L - R) - offset with saturation; |.| of -32768 is 32767 after the min below.
      const __m256i d = _mm256_subs_epi16(_mm256_sub_epi16(left_rows[r], _mm256_mullo_epi16(v, n16)), offset);
      const __m256i a = _mm256_and_si256(_mm256_min_epu16(_mm256_abs_epi16(d), _mm256_set1_epi16(32767)), lane_mask);
      acc = _mm256_add_epi32(acc, _mm256_madd_epi16(a, ones));
    }
    alignas(32) int lanes[8];
    _mm256_store_si256(reinterpret_cast<__m256i*>(lanes), acc);
    sads[k] = lanes[0] + lanes[1] + lanes[2] + lanes[3] + lanes[4] + lanes[5] + lanes[6] + lanes[7];
  }
}

#endif

void ZeroMeanSads(bool avx2, const cv::Mat& limg, int xl, int yl, const cv::Mat& rimg, int xr_begin, int count, int w,
                  int* sads) {
#if defined(__x86_64__) || defined(__i386__)
  if (avx2 && 2 * w + 1 <= 11 && xl - w + 16 <= limg.cols && xr_begin + count - 1 - w + 16 <= rimg.cols) {
    return ZeroMeanSadsAvx2(limg, xl, yl, rimg, xr_begin, count, w, sads);
  }
#endif
  ZeroMeanSadsBaseline(limg, xl, yl, rimg, xr_begin, count, w, sads);
}

}  // namespace

StereoStats MatchStereo(const Keypoints& right, const ImagePyramid& left_pyramid, const ImagePyramid& right_pyramid,
                        const ScalePyramid& scales, double fx, double baseline_m, const StereoOptions& options,
                        Keypoints* left) {
  FLATSLAM_CHECK(left != nullptr, "MatchStereo: null left keypoints");
  FLATSLAM_CHECK(options.Check(), "MatchStereo: invalid StereoOptions");
  FLATSLAM_CHECK(fx > 0 && baseline_m > 0, "MatchStereo: fx and baseline must be > 0, got ", fx, ", ", baseline_m);
  FLATSLAM_CHECK(!left_pyramid.levels.empty() && left_pyramid.levels.size() == right_pyramid.levels.size() &&
                     static_cast<int>(left_pyramid.levels.size()) == scales.levels,
                 "MatchStereo: pyramids must both have ", scales.levels, " levels");
  for (size_t l = 0; l < left_pyramid.levels.size(); ++l) {
    FLATSLAM_CHECK(left_pyramid.levels[l].size() == right_pyramid.levels[l].size() &&
                       left_pyramid.levels[l].type() == CV_8UC1 && right_pyramid.levels[l].type() == CV_8UC1,
                   "MatchStereo: left and right pyramid level ", l, " differ in size or type");
  }
  FLATSLAM_CHECK(left->consistent() && right.consistent(), "MatchStereo: keypoint columns differ in length");

  const size_t n_left = left->size();
  std::fill(left->right_u.begin(), left->right_u.end(), -1.f);
  std::fill(left->depth.begin(), left->depth.end(), -1.f);
  StereoStats stats;
  if (n_left == 0 || right.empty()) return stats;

  const int rows = left_pyramid.levels[0].rows;
  const double bf = fx * baseline_m;
  const float min_disparity = 0.f;
  const float max_disparity = static_cast<float>(options.min_depth_m > 0 ? bf / options.min_depth_m : fx);

  // Right keypoints by row (CSR): keypoint j is listed on every row within its octave's radius.
  std::vector<int> row_start(rows + 1, 0);
  auto row_span = [&](size_t j, int* r0, int* r1) {
    const float v = right.uv[j].y();
    const float radius = options.row_radius * scales.scale[std::min<int>(right.octave[j], scales.levels - 1)];
    *r0 = std::max(0, static_cast<int>(std::floor(v - radius)));
    *r1 = std::min(rows - 1, static_cast<int>(std::ceil(v + radius)));
  };
  for (size_t j = 0; j < right.size(); ++j) {
    int r0, r1;
    row_span(j, &r0, &r1);
    for (int r = r0; r <= r1; ++r) ++row_start[r + 1];
  }
  for (int r = 0; r < rows; ++r) row_start[r + 1] += row_start[r];
  std::vector<uint32_t> row_entries(row_start[rows]);
  {
    std::vector<int> fill(row_start.begin(), row_start.end() - 1);
    for (size_t j = 0; j < right.size(); ++j) {
      int r0, r1;
      row_span(j, &r0, &r1);
      for (int r = r0; r <= r1; ++r) row_entries[fill[r]++] = static_cast<uint32_t>(j);
    }
  }

  // Per left keypoint: 0 = no descriptor match, 1 = descriptor match only, 2 = refined.
  std::vector<uint8_t> stage(n_left, 0);
  std::vector<int> sad_score(n_left, std::numeric_limits<int>::max());
  const int w = options.sad_half_window, search = options.sad_search_radius;
  const bool avx2 = options.use_avx2 && HasAvx2();

  tbb::parallel_for(tbb::blocked_range<size_t>(0, n_left, 64), [&](const tbb::blocked_range<size_t>& range) {
    std::vector<int> sads(2 * search + 1);
    for (size_t i = range.begin(); i != range.end(); ++i) {
      const float ul = left->uv[i].x(), vl = left->uv[i].y();
      const int row = static_cast<int>(std::lround(vl));
      if (row < 0 || row >= rows) continue;
      const int level = std::min<int>(left->octave[i], scales.levels - 1);
      const float min_u = ul - max_disparity, max_u = ul - min_disparity;

      int best_distance = options.descriptor_threshold, best = -1;
      for (int e = row_start[row]; e < row_start[row + 1]; ++e) {
        const uint32_t j = row_entries[e];
        if (std::abs(static_cast<int>(right.octave[j]) - level) > options.octave_radius) continue;
        const float ur = right.uv[j].x();
        if (ur < min_u || ur > max_u) continue;
        const int d = Hamming(left->descriptor[i], right.descriptor[j]);
        if (d < best_distance) {
          best_distance = d;
          best = static_cast<int>(j);
        }
      }
      if (best < 0) continue;
      stage[i] = 1;

      // SAD along the row on the left keypoint's level, around the matched right keypoint.
      const cv::Mat& limg = left_pyramid.levels[level];
      const cv::Mat& rimg = right_pyramid.levels[level];
      const Eigen::Vector2f pl = left_pyramid.ToLevel(left->uv[i], level);
      const int xl = static_cast<int>(std::lround(pl.x())), yl = static_cast<int>(std::lround(pl.y()));
      const int xr0 =
          static_cast<int>(std::lround(right_pyramid.ToLevel(Eigen::Vector2f(right.uv[best].x(), vl), level).x()));
      if (yl - w < 0 || yl + w >= limg.rows || xl - w < 0 || xl + w >= limg.cols) continue;
      if (xr0 - search - w < 0 || xr0 + search + w >= rimg.cols) continue;

      ZeroMeanSads(avx2, limg, xl, yl, rimg, xr0 - search, 2 * search + 1, w, sads.data());
      int best_sad = std::numeric_limits<int>::max(), best_offset = 0;
      for (int k = -search; k <= search; ++k) {
        if (sads[k + search] < best_sad) {
          best_sad = sads[k + search];
          best_offset = k;
        }
      }
      // A minimum on the border of the search may lie outside it.
      if (best_offset == -search || best_offset == search) continue;
      const double s_minus = sads[best_offset + search - 1], s0 = sads[best_offset + search],
                   s_plus = sads[best_offset + search + 1];
      const double curvature = s_minus + s_plus - 2.0 * s0;
      const double delta = curvature > 0 ? (s_minus - s_plus) / (2.0 * curvature) : 0.0;
      if (delta < -1.0 || delta > 1.0) continue;

      const float xr = static_cast<float>(xr0 + best_offset + delta);
      // The SAD found the left patch centred on the pixel xl; the keypoint lies (sub-pixel) off it
      // by as much in both images.
      const float patch_ul = left_pyramid.FromLevel(Eigen::Vector2f(static_cast<float>(xl), pl.y()), level).x();
      const float ur =
          right_pyramid.FromLevel(Eigen::Vector2f(xr, static_cast<float>(yl)), level).x() + (ul - patch_ul);
      // The rig's own offset comes off: where an exact rig would have shown the point.
      const float exact_ur = ur + static_cast<float>(options.disparity_offset_px);
      const float disparity = ul - exact_ur;
      if (disparity <= min_disparity || disparity >= max_disparity) continue;
      stage[i] = 2;
      sad_score[i] = best_sad;
      left->right_u[i] = exact_ur;
      left->depth[i] = static_cast<float>(bf / disparity);
    }
  });

  // Outliers: a SAD far above the median marks a wrong or badly localised match.
  std::vector<int> scores;
  for (size_t i = 0; i < n_left; ++i) {
    stats.descriptor_matches += stage[i] >= 1;
    if (stage[i] == 2) scores.push_back(sad_score[i]);
  }
  stats.refined = static_cast<int>(scores.size());
  if (scores.empty()) return stats;
  std::nth_element(scores.begin(), scores.begin() + scores.size() / 2, scores.end());
  const double limit = options.outlier_factor * scores[scores.size() / 2];
  for (size_t i = 0; i < n_left; ++i) {
    if (stage[i] != 2) continue;
    if (sad_score[i] > limit) {
      left->right_u[i] = -1.f;
      left->depth[i] = -1.f;
    } else {
      ++stats.matched;
    }
  }
  return stats;
}

int DepthFromImage(const cv::Mat& depth_m, double fx, double virtual_baseline_m, Keypoints* keypoints) {
  FLATSLAM_CHECK(keypoints != nullptr, "DepthFromImage: null keypoints");
  FLATSLAM_CHECK(!depth_m.empty() && depth_m.type() == CV_32FC1,
                 "DepthFromImage: depth image must be a non-empty CV_32FC1 in metres, got type ", depth_m.type());
  FLATSLAM_CHECK(fx > 0 && virtual_baseline_m > 0, "DepthFromImage: fx and virtual baseline must be > 0, got ", fx,
                 ", ", virtual_baseline_m);
  const size_t n = keypoints->size();
  keypoints->right_u.assign(n, -1.f);
  keypoints->depth.assign(n, -1.f);
  const double bf = fx * virtual_baseline_m;
  int count = 0;
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector2f& uv = keypoints->uv[i];
    const long x = std::lround(uv.x()), y = std::lround(uv.y());
    if (x < 0 || y < 0 || x >= depth_m.cols || y >= depth_m.rows) continue;
    const float d = depth_m.at<float>(static_cast<int>(y), static_cast<int>(x));
    if (!(d > 0) || !std::isfinite(d)) continue;
    keypoints->depth[i] = d;
    keypoints->right_u[i] = static_cast<float>(uv.x() - bf / d);
    ++count;
  }
  return count;
}

}  // namespace flatslam
