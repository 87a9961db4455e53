#include "matching/matcher.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <unordered_set>

#include "core/requirements.h"

namespace flatslam {

namespace {

constexpr float kTwoPi = 6.28318530717958647692f;

// Angle differences of matches in 30 bins; matches outside the three dominant bins are
// rejected (a bin is kept only if it holds at least a tenth of the largest one).
class RotationHistogram {
 public:
  void Add(float angle_diff, uint32_t id) {
    float a = std::fmod(angle_diff, kTwoPi);
    if (a < 0) a += kTwoPi;
    const int bin = std::min(kBins - 1, static_cast<int>(a / kTwoPi * kBins));
    bins_[bin].push_back(id);
  }
  [[nodiscard]] std::vector<uint32_t> Rejected() const {
    std::array<int, kBins> order;
    for (int i = 0; i < kBins; ++i) order[i] = i;
    std::partial_sort(order.begin(), order.begin() + 3, order.end(),
                      [&](int a, int b) { return bins_[a].size() > bins_[b].size(); });
    const size_t largest = bins_[order[0]].size();
    std::array<bool, kBins> keep{};
    for (int k = 0; k < 3; ++k)
      if (k == 0 || bins_[order[k]].size() * 10 >= largest) keep[order[k]] = true;
    std::vector<uint32_t> out;
    for (int i = 0; i < kBins; ++i)
      if (!keep[i]) out.insert(out.end(), bins_[i].begin(), bins_[i].end());
    return out;
  }

 private:
  static constexpr int kBins = 30;
  std::array<std::vector<uint32_t>, kBins> bins_;
};

std::unordered_set<PointHandle> MatchedPoints(const TrackedFrame& frame) {
  std::unordered_set<PointHandle> set;
  set.reserve(frame.points.size());
  for (PointHandle p : frame.points)
    if (!p.is_null()) set.insert(p);
  return set;
}

// Keypoint k of current can take a projected point: still free, on a level in [min_level,
// max_level], and (stereo) its right-image x within r of the predicted right_u.
bool Usable(const TrackedFrame& current, uint32_t k, int min_level, int max_level, double right_u, bool stereo,
            float r) {
  if (!current.points[k].is_null()) return false;
  const int o = current.keypoints.octave[k];
  if (o < min_level || o > max_level) return false;
  if (stereo && current.keypoints.right_u[k] >= 0 && std::abs(right_u - current.keypoints.right_u[k]) > r) return false;
  return true;
}

// Level at which a point at `distance` is expected, from its scale-invariance range.
int PredictLevel(const MapPoint& point, double distance, const ScalePyramid& pyramid) {
  const double ratio = point.max_distance / distance;
  const int level = static_cast<int>(std::ceil(std::log(ratio) / pyramid.log_scale_factor));
  return std::clamp(level, 0, pyramid.levels - 1);
}

// Shared body of the frame- and keyframe-sourced projection searches.
template <class GetPoint, class GetOctave, class GetAngle>
int ProjectAndMatch(TrackedFrame& current, size_t n, GetPoint get_point, GetOctave get_octave, GetAngle get_angle,
                    const Map& map, const CameraGeometry& g, float radius, const MatcherOptions& options) {
  std::unordered_set<PointHandle> taken = MatchedPoints(current);
  RotationHistogram histogram;
  std::vector<uint32_t> candidates;
  int matches = 0;
  for (size_t i = 0; i < n; ++i) {
    const PointHandle p = get_point(i);
    if (p.is_null() || taken.count(p)) continue;
    const MapPoint* point = map.points().try_get(p);
    if (!point) continue;
    const Eigen::Vector3d Xc = current.T_cam_world * point->position;
    double u, v;
    if (!g.Project(Xc, &u, &v)) continue;
    const double inv_z = 1.0 / Xc.z();
    const int octave = get_octave(i);
    const float r = radius * g.pyramid.scale[octave];
    candidates.clear();
    current.grid.Query(static_cast<float>(u), static_cast<float>(v), r, &candidates);
    int best = 257;
    int best_index = -1;
    for (uint32_t k : candidates) {
      if (!Usable(current, k, octave - 1, octave + 1, u - g.bf * inv_z, g.bf > 0, r)) continue;
      const int d = Hamming(point->descriptor, current.keypoints.descriptor[k]);
      if (d < best) {
        best = d;
        best_index = static_cast<int>(k);
      }
    }
    if (best_index < 0 || best > options.max_distance) continue;
    current.points[best_index] = p;
    taken.insert(p);
    ++matches;
    histogram.Add(get_angle(i) - current.keypoints.angle[best_index], static_cast<uint32_t>(best_index));
  }
  if (options.check_orientation) {
    for (uint32_t k : histogram.Rejected()) {
      current.points[k] = PointHandle::null();
      --matches;
    }
  }
  return matches;
}

// Appends the keypoints within kStep pixels of the image segment from p to q (the epipolar
// line of a depth range); stamp deduplicates across overlapping queries.
void SegmentBand(Eigen::Vector2d p, Eigen::Vector2d q, const FeatureGrid& grid, std::vector<uint32_t>* out,
                 std::vector<uint32_t>* stamp, uint32_t stamp_value) {
  constexpr float kStep = 12.0f;
  const double length = (q - p).norm();
  const int steps = std::max(1, static_cast<int>(std::ceil(length / kStep)));
  std::vector<uint32_t> found;
  for (int k = 0; k <= steps; ++k) {
    const Eigen::Vector2d x = p + (q - p) * (static_cast<double>(k) / steps);
    found.clear();
    grid.Query(static_cast<float>(x.x()), static_cast<float>(x.y()), kStep, &found);
    for (uint32_t i : found) {
      if ((*stamp)[i] == stamp_value) continue;
      (*stamp)[i] = stamp_value;
      out->push_back(i);
    }
  }
}

// Pixel segment in view 2 where a view-1 ray (normalized direction ray1) lands for depths in
// [near, far], clipped to points in front of camera 2 and to the image; false when empty.
bool EpipolarSegment(const Eigen::Vector3d& ray1, double near, double far, const Eigen::Isometry3d& T_2_1,
                     const CameraGeometry& g, Eigen::Vector2d* p, Eigen::Vector2d* q) {
  constexpr double kMinZ = 0.01;
  const Eigen::Vector3d a = T_2_1 * (near * ray1), b = T_2_1 * (far * ray1);
  Eigen::Vector3d from = a, to = b;
  if (from.z() < kMinZ && to.z() < kMinZ) return false;
  if (from.z() < kMinZ) from = a + (b - a) * ((kMinZ - a.z()) / (b.z() - a.z()));
  if (to.z() < kMinZ) to = a + (b - a) * ((kMinZ - a.z()) / (b.z() - a.z()));
  *p = g.camera.Project(from);
  *q = g.camera.Project(to);
  // Clip to the image (Liang-Barsky on the segment p + s (q - p)).
  double s0 = 0, s1 = 1;
  const Eigen::Vector2d d = *q - *p;
  const double lo[2] = {0, 0}, hi[2] = {static_cast<double>(g.camera.width), static_cast<double>(g.camera.height)};
  for (int axis = 0; axis < 2; ++axis) {
    for (int side = 0; side < 2; ++side) {
      const double edge = side == 0 ? lo[axis] : hi[axis];
      // Inside this edge where num + s * rate >= 0.
      const double num = side == 0 ? (*p)(axis)-edge : edge - (*p)(axis);
      const double rate = side == 0 ? d(axis) : -d(axis);
      if (rate == 0) {
        if (num < 0) return false;
        continue;
      }
      const double t = -num / rate;
      if (rate > 0)
        s0 = std::max(s0, t);
      else
        s1 = std::min(s1, t);
    }
  }
  if (s0 > s1) return false;
  const Eigen::Vector2d start = *p + s0 * d, end = *p + s1 * d;
  *p = start;
  *q = end;
  return true;
}

}  // namespace

int MatchByProjection(TrackedFrame& current, const TrackedFrame& source, const Map& map, const CameraGeometry& geometry,
                      float radius, const MatcherOptions& options) {
  return ProjectAndMatch(
      current, source.size(), [&](size_t i) { return source.outlier[i] ? PointHandle::null() : source.points[i]; },
      [&](size_t i) { return static_cast<int>(source.keypoints.octave[i]); },
      [&](size_t i) { return source.keypoints.angle[i]; }, map, geometry, radius, options);
}

int MatchByProjection(TrackedFrame& current, const KeyFrame& source, const Map& map, const CameraGeometry& geometry,
                      float radius, const MatcherOptions& options) {
  return ProjectAndMatch(
      current, source.size(), [&](size_t i) { return source.points[i]; },
      [&](size_t i) { return static_cast<int>(source.octave[i]); }, [&](size_t i) { return source.angle[i]; }, map,
      geometry, radius, options);
}

int MatchLocalPoints(TrackedFrame& current, const Map& map, std::span<const PointHandle> points,
                     const CameraGeometry& g, float radius_scale, const MatcherOptions& options,
                     std::vector<PointHandle>* seen) {
  const std::unordered_set<PointHandle> taken = MatchedPoints(current);
  const Eigen::Vector3d center = current.T_cam_world.inverse().translation();
  std::vector<uint32_t> candidates;
  int matches = 0;
  for (PointHandle p : points) {
    if (taken.count(p)) continue;
    const MapPoint* point = map.points().try_get(p);
    if (!point) continue;
    const Eigen::Vector3d Xc = current.T_cam_world * point->position;
    double u, v;
    if (!g.Project(Xc, &u, &v)) continue;
    const double inv_z = 1.0 / Xc.z();
    const Eigen::Vector3d ray = point->position - center;
    const double distance = ray.norm();
    if (distance < 0.8 * point->min_distance || distance > 1.2 * point->max_distance) continue;
    const double view_cos = ray.dot(point->normal) / distance;
    if (view_cos < 0.5) continue;
    const int level = PredictLevel(*point, distance, g.pyramid);
    if (seen) seen->push_back(p);
    const float r = radius_scale * (view_cos > 0.998 ? 2.5f : 4.0f) * g.pyramid.scale[level];
    candidates.clear();
    current.grid.Query(static_cast<float>(u), static_cast<float>(v), r, &candidates);
    int best = 257, second = 257, best_level = -1, second_level = -1, best_index = -1;
    for (uint32_t k : candidates) {
      if (!Usable(current, k, level - 1, level, u - g.bf * inv_z, g.bf > 0, r)) continue;
      const int o = current.keypoints.octave[k];
      const int d = Hamming(point->descriptor, current.keypoints.descriptor[k]);
      if (d < best) {
        second = best;
        second_level = best_level;
        best = d;
        best_level = o;
        best_index = static_cast<int>(k);
      } else if (d < second) {
        second = d;
        second_level = o;
      }
    }
    if (best_index < 0 || best > options.max_distance) continue;
    if (best_level == second_level && best > options.nn_ratio * second) continue;
    current.points[best_index] = p;
    ++matches;
  }
  return matches;
}

std::vector<std::pair<uint32_t, uint32_t>> MatchForInitialization(const TrackedFrame& first, const TrackedFrame& second,
                                                                  float window, const MatcherOptions& options) {
  std::vector<int> matched_in_2(second.size(), -1), distance_2(second.size(), 257);
  std::vector<uint32_t> candidates;
  for (uint32_t i1 = 0; i1 < first.size(); ++i1) {
    candidates.clear();
    second.grid.Query(first.keypoints.uv[i1].x(), first.keypoints.uv[i1].y(), window, &candidates);
    int best = 257, second_best = 257, best_index = -1;
    for (uint32_t i2 : candidates) {
      if (second.keypoints.octave[i2] != first.keypoints.octave[i1]) continue;
      const int d = Hamming(first.keypoints.descriptor[i1], second.keypoints.descriptor[i2]);
      if (distance_2[i2] <= d) continue;
      if (d < best) {
        second_best = best;
        best = d;
        best_index = static_cast<int>(i2);
      } else if (d < second_best) {
        second_best = d;
      }
    }
    if (best_index < 0 || best > options.max_distance_strict || best >= 0.9 * second_best) continue;
    if (matched_in_2[best_index] >= 0) matched_in_2[best_index] = -1;  // contested: drop the old one
    matched_in_2[best_index] = static_cast<int>(i1);
    distance_2[best_index] = best;
  }
  RotationHistogram histogram;
  for (uint32_t i2 = 0; i2 < second.size(); ++i2)
    if (matched_in_2[i2] >= 0) histogram.Add(first.keypoints.angle[matched_in_2[i2]] - second.keypoints.angle[i2], i2);
  if (options.check_orientation)
    for (uint32_t i2 : histogram.Rejected()) matched_in_2[i2] = -1;
  std::vector<std::pair<uint32_t, uint32_t>> out;
  for (uint32_t i2 = 0; i2 < second.size(); ++i2)
    if (matched_in_2[i2] >= 0) out.emplace_back(static_cast<uint32_t>(matched_in_2[i2]), i2);
  return out;
}

Eigen::Matrix3d FundamentalBetween(const KeyFrame& kf1, const KeyFrame& kf2, const PinholeCamera& camera) {
  const Eigen::Isometry3d T_2_1 = kf2.T_cam_world * kf1.T_cam_world.inverse();
  const Eigen::Vector3d t = T_2_1.translation();
  Eigen::Matrix3d tx;
  tx << 0, -t.z(), t.y(), t.z(), 0, -t.x(), -t.y(), t.x(), 0;
  const Eigen::Matrix3d E = tx * T_2_1.linear();
  const Eigen::Matrix3d K_inv = camera.K().inverse();
  return K_inv.transpose() * E * K_inv;
}

std::vector<std::pair<uint32_t, uint32_t>> MatchForTriangulation(const KeyFrame& kf1, const KeyFrame& kf2,
                                                                 const Eigen::Matrix3d& F_2_1,
                                                                 std::pair<double, double> depth_range,
                                                                 const CameraGeometry& g,
                                                                 const MatcherOptions& options) {
  // Epipole: the centre of kf1 seen from kf2; mono matches next to it have no parallax.
  const Eigen::Vector3d c1_in_2 = kf2.T_cam_world * kf1.camera_center();
  const double eu = g.camera.fx * c1_in_2.x() / c1_in_2.z() + g.camera.cx;
  const double ev = g.camera.fy * c1_in_2.y() / c1_in_2.z() + g.camera.cy;
  std::vector<int> matched_in_2(kf2.size(), -1);
  std::vector<int> best_distance_2(kf2.size(), 257);
  RotationHistogram histogram;
  const Eigen::Isometry3d T_2_1 = kf2.T_cam_world * kf1.T_cam_world.inverse();
  // Monocular keyframes with both bags of words: candidates are the kf2 keypoints under the same
  // vocabulary node (tested below for lying near the epipolar segment); else a grid search
  // along the segment. The grid finds more matches, the words far fewer candidates: on monocular
  // KITTI 07 local mapping takes a third of the time; with stereo or depth, where most rays have
  // a short search, the fuller grid search gave the lower trajectory error on KITTI 06 and the
  // synthetic town.
  const bool by_words = g.bf <= 0 && !kf1.bow_features.empty() && !kf2.bow_features.empty();
  // Only kf2 keypoints without a map point can take a new one: the grid holds those alone.
  FeatureGrid grid2;
  grid2.BuildWhere(kf2.uv, g.camera.width, g.camera.height, [&](size_t i) { return kf2.points[i].is_null(); });
  std::vector<uint32_t> candidates, stamp(by_words ? 0 : kf2.size(), 0);
  uint32_t stamp_value = 0;
  constexpr double kBand = 12.0;  // pixels around the epipolar segment of the depth range

  // Where i1 may land in kf2: a disc around the projection of its measured depth (stereo/RGB-D),
  // else the epipolar segment of the depth range. False when it cannot land in the image.
  struct Region {
    bool disc = false;
    Eigen::Vector2d p, q;  // disc: centre p; segment: from p to q
    double radius = 0;
    Eigen::Vector3d line;  // epipolar line of i1 in kf2
    double line_norm2 = 0;
  };
  auto region_of = [&](uint32_t i1, Region* r) {
    r->line = F_2_1 * Eigen::Vector3d(kf1.uv[i1].x(), kf1.uv[i1].y(), 1.0);
    r->line_norm2 = r->line.x() * r->line.x() + r->line.y() * r->line.y();
    if (r->line_norm2 <= 0) return false;
    if (kf1.right_u[i1] >= 0 && kf1.depth[i1] > 0) {
      const float z = kf1.depth[i1];
      const Eigen::Vector3d X1((kf1.uv[i1].x() - g.camera.cx) / g.camera.fx * z,
                               (kf1.uv[i1].y() - g.camera.cy) / g.camera.fy * z, z);
      double u, v;
      if (!g.Project(T_2_1 * X1, &u, &v)) return false;
      r->disc = true;
      r->p = {u, v};
      // Stereo depth is uncertain far away: search a radius that grows with disparity error.
      r->radius = 10.0 * g.pyramid.scale[kf1.octave[i1]];
      return true;
    }
    const Eigen::Vector3d ray1((kf1.uv[i1].x() - g.camera.cx) / g.camera.fx,
                               (kf1.uv[i1].y() - g.camera.cy) / g.camera.fy, 1.0);
    r->disc = false;
    r->radius = kBand;
    return EpipolarSegment(ray1, depth_range.first, depth_range.second, T_2_1, g, &r->p, &r->q);
  };
  auto inside = [](const Region& r, double u, double v) {
    const Eigen::Vector2d x(u, v);
    if (r.disc) return (x - r.p).cwiseAbs().maxCoeff() <= r.radius;
    const Eigen::Vector2d d = r.q - r.p;
    const double len2 = d.squaredNorm();
    const double t = len2 > 0 ? std::clamp((x - r.p).dot(d) / len2, 0.0, 1.0) : 0.0;
    return (x - (r.p + t * d)).norm() <= r.radius;
  };
  // The best kf2 keypoint among the candidates; one kf2 keypoint per kf1 keypoint, the closer
  // descriptor wins.
  auto consider = [&](uint32_t i1, const Region& r, std::span<const uint32_t> pool, bool check_region) {
    const bool stereo1 = kf1.right_u[i1] >= 0;
    int best = options.max_distance_strict + 1;
    int best_index = -1;
    for (uint32_t i2 : pool) {
      if (!kf2.points[i2].is_null()) continue;
      const int d = Hamming(kf1.descriptor[i1], kf2.descriptor[i2]);
      if (d >= best) continue;
      const bool stereo2 = kf2.right_u[i2] >= 0;
      const double u2 = kf2.uv[i2].x(), v2 = kf2.uv[i2].y();
      if (!stereo1 && !stereo2) {
        const double de = (u2 - eu) * (u2 - eu) + (v2 - ev) * (v2 - ev);
        if (de < 100.0 * g.pyramid.scale[kf2.octave[i2]]) continue;
      }
      const double num = r.line.x() * u2 + r.line.y() * v2 + r.line.z();
      if (num * num / r.line_norm2 >= 3.84 * g.pyramid.sigma2[kf2.octave[i2]]) continue;
      if (check_region && !inside(r, u2, v2)) continue;
      best = d;
      best_index = static_cast<int>(i2);
    }
    if (best_index < 0) return;
    if (matched_in_2[best_index] >= 0 && best_distance_2[best_index] <= best) return;
    matched_in_2[best_index] = static_cast<int>(i1);
    best_distance_2[best_index] = best;
  };

  Region region;
  // A measured depth bounds the search to a small disc: the grid finds it cheaply and completely.
  // Rays without depth search a long epipolar segment: the vocabulary narrows it when it can.
  for (uint32_t i1 = 0; i1 < kf1.size(); ++i1) {
    if (!kf1.points[i1].is_null() || !(kf1.right_u[i1] >= 0 && kf1.depth[i1] > 0)) continue;
    if (!region_of(i1, &region)) continue;
    candidates.clear();
    grid2.Query(static_cast<float>(region.p.x()), static_cast<float>(region.p.y()), static_cast<float>(region.radius),
                &candidates);
    consider(i1, region, candidates, false);
  }
  auto without_depth = [&](uint32_t i1) { return !(kf1.right_u[i1] >= 0 && kf1.depth[i1] > 0); };
  if (by_words) {
    const FeatureVector& f1 = kf1.bow_features;
    const FeatureVector& f2 = kf2.bow_features;
    size_t a = 0, b = 0;
    while (a < f1.size() && b < f2.size()) {
      if (f1[a].first < f2[b].first) {
        ++a;
        continue;
      }
      if (f2[b].first < f1[a].first) {
        ++b;
        continue;
      }
      const uint32_t node = f1[a].first;
      size_t ea = a, eb = b;
      while (ea < f1.size() && f1[ea].first == node) ++ea;
      while (eb < f2.size() && f2[eb].first == node) ++eb;
      candidates.clear();
      for (size_t y = b; y < eb; ++y) candidates.push_back(f2[y].second);
      for (size_t x = a; x < ea; ++x) {
        const uint32_t i1 = f1[x].second;
        if (!kf1.points[i1].is_null() || !without_depth(i1) || !region_of(i1, &region)) continue;
        consider(i1, region, candidates, true);
      }
      a = ea;
      b = eb;
    }
  } else {
    for (uint32_t i1 = 0; i1 < kf1.size(); ++i1) {
      if (!kf1.points[i1].is_null() || !without_depth(i1) || !region_of(i1, &region)) continue;
      candidates.clear();
      SegmentBand(region.p, region.q, grid2, &candidates, &stamp, ++stamp_value);
      consider(i1, region, candidates, false);
    }
  }
  std::vector<std::pair<uint32_t, uint32_t>> out;
  for (uint32_t i2 = 0; i2 < kf2.size(); ++i2) {
    if (matched_in_2[i2] < 0) continue;
    histogram.Add(kf1.angle[matched_in_2[i2]] - kf2.angle[i2], i2);
  }
  std::vector<uint8_t> rejected(kf2.size(), 0);
  if (options.check_orientation)
    for (uint32_t i2 : histogram.Rejected()) rejected[i2] = 1;
  for (uint32_t i2 = 0; i2 < kf2.size(); ++i2)
    if (matched_in_2[i2] >= 0 && !rejected[i2]) out.emplace_back(static_cast<uint32_t>(matched_in_2[i2]), i2);
  return out;
}

std::vector<std::pair<PointHandle, uint32_t>> FindFusion(const Map& map, KeyFrameHandle kf_handle,
                                                         std::span<const PointHandle> points, const CameraGeometry& g,
                                                         const MatcherOptions& options) {
  const KeyFrame& kf = map.keyframe(kf_handle);
  FeatureGrid grid;
  grid.Build(kf.uv, g.camera.width, g.camera.height);
  std::vector<uint32_t> candidates;
  std::vector<std::pair<PointHandle, uint32_t>> matches;
  for (PointHandle p : points) {
    const MapPoint* point = map.points().try_get(p);
    if (!point) continue;
    // The geometric tests first: they read the point alone, its observations live elsewhere.
    const Eigen::Vector3d Xc = kf.T_cam_world * point->position;
    double u, v;
    if (!g.Project(Xc, &u, &v)) continue;
    const double inv_z = 1.0 / Xc.z();
    const Eigen::Vector3d ray = point->position - kf.camera_center();
    const double distance = ray.norm();
    if (distance < 0.8 * point->min_distance || distance > 1.2 * point->max_distance) continue;
    if (ray.dot(point->normal) < 0.5 * distance) continue;
    if (std::any_of(point->observations.begin(), point->observations.end(),
                    [&](const Observation& o) { return o.keyframe == kf_handle; }))
      continue;
    const int level = PredictLevel(*point, distance, g.pyramid);
    const float r = options.fusion_radius * g.pyramid.scale[level];
    candidates.clear();
    grid.Query(static_cast<float>(u), static_cast<float>(v), r, &candidates);
    int best = 257, best_index = -1;
    for (uint32_t k : candidates) {
      const int o = kf.octave[k];
      if (o < level - 1 || o > level) continue;
      const double eu = u - kf.uv[k].x(), ev = v - kf.uv[k].y();
      double e2 = eu * eu + ev * ev;
      double gate = 5.991;
      if (g.bf > 0 && kf.right_u[k] >= 0) {
        const double er = (u - g.bf * inv_z) - kf.right_u[k];
        e2 += er * er;
        gate = 7.8;
      }
      if (e2 * g.pyramid.inv_sigma2[o] > gate) continue;
      const int d = Hamming(point->descriptor, kf.descriptor[k]);
      if (d < best) {
        best = d;
        best_index = static_cast<int>(k);
      }
    }
    if (best_index < 0 || best > options.max_distance_strict) continue;
    matches.emplace_back(p, static_cast<uint32_t>(best_index));
  }
  return matches;
}

int ApplyFusion(Map& map, KeyFrameHandle kf_handle, std::span<const std::pair<PointHandle, uint32_t>> matches) {
  int fused = 0;
  for (const auto& [p, keypoint] : matches) {
    const MapPoint* point = map.points().try_get(p);
    if (!point || std::any_of(point->observations.begin(), point->observations.end(),
                              [&](const Observation& o) { return o.keyframe == kf_handle; }))
      continue;
    const PointHandle existing = map.keyframe(kf_handle).points[keypoint];
    if (existing.is_null()) {
      map.AddObservation(p, kf_handle, keypoint);
    } else if (existing != p) {
      const size_t n_existing = map.point(existing).observations.size();
      if (n_existing >= point->observations.size())
        map.ReplacePoint(p, existing);
      else
        map.ReplacePoint(existing, p);
    }
    ++fused;
  }
  return fused;
}

int FusePoints(Map& map, KeyFrameHandle kf, std::span<const PointHandle> points, const CameraGeometry& g,
               const MatcherOptions& options) {
  return ApplyFusion(map, kf, FindFusion(map, kf, points, g, options));
}

}  // namespace flatslam

namespace flatslam {
namespace {

// Walks two direct indexes node by node; for each usable keypoint of A the best usable keypoint
// of B under the same node, ratio-tested; each keypoint of B taken once. Orientation-checked.
template <class UsableA, class UsableB>
std::vector<std::pair<uint32_t, uint32_t>> MatchDirectIndex(const FeatureVector& fa, std::span<const Descriptor> da,
                                                            std::span<const float> angle_a, const FeatureVector& fb,
                                                            std::span<const Descriptor> db,
                                                            std::span<const float> angle_b, UsableA usable_a,
                                                            UsableB usable_b, const MatcherOptions& options,
                                                            float ratio) {
  std::vector<std::pair<uint32_t, uint32_t>> pairs;
  std::unordered_set<uint32_t> taken_b;
  size_t ia = 0, ib = 0;
  while (ia < fa.size() && ib < fb.size()) {
    const uint32_t na = fa[ia].first, nb = fb[ib].first;
    if (na < nb) {
      ++ia;
      continue;
    }
    if (nb < na) {
      ++ib;
      continue;
    }
    size_t ea = ia, eb = ib;
    while (ea < fa.size() && fa[ea].first == na) ++ea;
    while (eb < fb.size() && fb[eb].first == nb) ++eb;
    for (size_t x = ia; x < ea; ++x) {
      const uint32_t i = fa[x].second;
      if (!usable_a(i)) continue;
      int best = 257, second = 257;
      int best_j = -1;
      for (size_t y = ib; y < eb; ++y) {
        const uint32_t j = fb[y].second;
        if (!usable_b(j) || taken_b.count(j)) continue;
        const int d = Hamming(da[i], db[j]);
        if (d < best) {
          second = best;
          best = d;
          best_j = static_cast<int>(j);
        } else if (d < second) {
          second = d;
        }
      }
      if (best_j < 0 || best > options.max_distance_strict) continue;
      if (static_cast<float>(best) >= ratio * static_cast<float>(second)) continue;
      taken_b.insert(static_cast<uint32_t>(best_j));
      pairs.emplace_back(i, static_cast<uint32_t>(best_j));
    }
    ia = ea;
    ib = eb;
  }
  if (options.check_orientation && !pairs.empty()) {
    RotationHistogram histogram;
    for (uint32_t k = 0; k < pairs.size(); ++k) histogram.Add(angle_a[pairs[k].first] - angle_b[pairs[k].second], k);
    std::vector<bool> drop(pairs.size(), false);
    for (uint32_t k : histogram.Rejected()) drop[k] = true;
    std::vector<std::pair<uint32_t, uint32_t>> kept;
    for (size_t k = 0; k < pairs.size(); ++k)
      if (!drop[k]) kept.push_back(pairs[k]);
    pairs.swap(kept);
  }
  return pairs;
}

}  // namespace

int MatchByBow(TrackedFrame& frame, const KeyFrame& kf, const Map& map, const MatcherOptions& options, float ratio) {
  std::unordered_set<PointHandle> taken = MatchedPoints(frame);
  const auto pairs = MatchDirectIndex(
      kf.bow_features, kf.descriptor, kf.angle, frame.bow_features, frame.keypoints.descriptor, frame.keypoints.angle,
      [&](uint32_t i) { return map.points().contains(kf.points[i]) && !taken.count(kf.points[i]); },
      [&](uint32_t j) { return frame.points[j].is_null(); }, options, ratio);
  int matches = 0;
  for (const auto& [i, j] : pairs) {
    if (!taken.insert(kf.points[i]).second) continue;
    frame.points[j] = kf.points[i];
    ++matches;
  }
  return matches;
}

std::vector<std::pair<uint32_t, uint32_t>> MatchKeyFramesByBow(const KeyFrame& a, const Map& map_a, const KeyFrame& b,
                                                               const Map& map_b, const MatcherOptions& options,
                                                               float ratio) {
  return MatchDirectIndex(
      a.bow_features, a.descriptor, a.angle, b.bow_features, b.descriptor, b.angle,
      [&](uint32_t i) { return map_a.points().contains(a.points[i]); },
      [&](uint32_t j) { return map_b.points().contains(b.points[j]); }, options, ratio);
}

}  // namespace flatslam

namespace flatslam {

int MatchBySimilarity(const KeyFrame& kf, const Similarity3& S_cw, std::span<const PointHandle> points, const Map& map,
                      const CameraGeometry& g, float radius, const MatcherOptions& options,
                      std::vector<PointHandle>* matched) {
  matched->resize(kf.size(), PointHandle::null());
  FeatureGrid grid;
  grid.Build(kf.uv, g.camera.width, g.camera.height);
  std::unordered_set<PointHandle> taken;
  for (PointHandle p : *matched)
    if (!p.is_null()) taken.insert(p);
  const Eigen::Vector3d center = S_cw.inverse().t;  // camera centre in the world
  std::vector<uint32_t> candidates;
  int added = 0;
  for (PointHandle p : points) {
    if (taken.count(p)) continue;
    const MapPoint* point = map.points().try_get(p);
    if (!point) continue;
    const Eigen::Vector3d Xc = S_cw * point->position;
    double u, v;
    if (!g.Project(Xc, &u, &v)) continue;
    const Eigen::Vector3d ray = point->position - center;
    const double distance = ray.norm();
    if (distance < 0.8 * point->min_distance || distance > 1.2 * point->max_distance) continue;
    if (ray.dot(point->normal) < 0.5 * distance) continue;  // viewed from more than 60 degrees off
    const int level = PredictLevel(*point, distance, g.pyramid);
    const float r = radius * g.pyramid.scale[level];
    candidates.clear();
    grid.Query(static_cast<float>(u), static_cast<float>(v), r, &candidates);
    int best = 257, best_k = -1;
    for (uint32_t k : candidates) {
      if (!(*matched)[k].is_null()) continue;
      if (kf.octave[k] < level - 1 || kf.octave[k] > level) continue;
      const int d = Hamming(point->descriptor, kf.descriptor[k]);
      if (d < best) {
        best = d;
        best_k = static_cast<int>(k);
      }
    }
    if (best_k < 0 || best > options.max_distance_strict) continue;
    (*matched)[best_k] = p;
    taken.insert(p);
    ++added;
  }
  return added;
}

}  // namespace flatslam

namespace flatslam {

std::vector<PointCorrespondence> CorrespondencesOf(const KeyFrame& a, const Map& map_a, const KeyFrame& b,
                                                   const Map& map_b,
                                                   std::span<const std::pair<uint32_t, uint32_t>> pairs,
                                                   const ScalePyramid& pyramid) {
  std::vector<PointCorrespondence> out;
  out.reserve(pairs.size());
  for (const auto& [i, j] : pairs) {
    PointCorrespondence c;
    c.X1 = a.T_cam_world * map_a.point(a.points[i]).position;
    c.X2 = b.T_cam_world * map_b.point(b.points[j]).position;
    c.uv1 = a.uv[i].cast<double>();
    c.uv2 = b.uv[j].cast<double>();
    c.sigma2_1 = pyramid.sigma2[a.octave[i]];
    c.sigma2_2 = pyramid.sigma2[b.octave[j]];
    out.push_back(c);
  }
  return out;
}

}  // namespace flatslam
