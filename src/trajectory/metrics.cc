#include "trajectory/metrics.h"

#include <algorithm>
#include <cmath>
#include <numbers>

#include <Eigen/SVD>

#include "core/error.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

constexpr double kRadToDeg = 180.0 / std::numbers::pi;

// a^-1 * b with a general inverse, so slightly non-orthonormal file rotations (KITTI keeps
// ~6 digits) give an exact identity for identical poses, as the KITTI devkit does.
Eigen::Matrix4d Relative(const Eigen::Isometry3d& a, const Eigen::Isometry3d& b) {
  return a.matrix().inverse() * b.matrix();
}

// Error pose E = (gt_i^-1 gt_j)^-1 (est_i^-1 est_j), the convention of evo's RPE.
Eigen::Matrix4d RelativeError(const Eigen::Isometry3d& gt_i, const Eigen::Isometry3d& gt_j,
                              const Eigen::Isometry3d& est_i, const Eigen::Isometry3d& est_j) {
  return Relative(gt_i, gt_j).inverse() * Relative(est_i, est_j);
}

// Cumulative distance along the positions: out[0] = 0, out[i] = out[i-1] + |p_i - p_{i-1}|.
std::vector<double> PathDistances(const std::vector<Eigen::Isometry3d>& poses) {
  std::vector<double> dist(poses.size(), 0.0);
  for (size_t i = 1; i < poses.size(); ++i)
    dist[i] = dist[i - 1] + (poses[i].translation() - poses[i - 1].translation()).norm();
  return dist;
}

void CheckSameLength(const std::vector<Eigen::Isometry3d>& gt, const std::vector<Eigen::Isometry3d>& est,
                     const char* what) {
  FLATSLAM_CHECK(gt.size() == est.size(), what, ": ground truth has ", gt.size(), " matched poses but the estimate ",
                 est.size());
}

RpeResult RpeFromPairs(const std::vector<Eigen::Isometry3d>& gt, const std::vector<Eigen::Isometry3d>& est,
                       const std::vector<std::pair<size_t, size_t>>& ids) {
  RpeResult result;
  std::vector<double> trans, rot;
  trans.reserve(ids.size());
  rot.reserve(ids.size());
  for (auto [i, j] : ids) {
    const Eigen::Matrix4d e = RelativeError(gt[i], gt[j], est[i], est[j]);
    trans.push_back(e.block<3, 1>(0, 3).norm());
    rot.push_back(RotationAngle(e.topLeftCorner<3, 3>()) * kRadToDeg);
  }
  result.pairs = ids.size();
  result.translation_m = ComputeErrorStats(std::move(trans));
  result.rotation_deg = ComputeErrorStats(std::move(rot));
  return result;
}

int64_t SecondsToNs(double seconds) {
  return std::llround(seconds * 1e9);
}

}  // namespace

bool AssociationOptions::Check() const {
  return std::isfinite(max_diff_s) && max_diff_s >= 0 && std::isfinite(est_offset_s);
}

std::vector<IndexPair> AssociateByTime(const Trajectory& gt, const Trajectory& est, const AssociationOptions& options) {
  FLATSLAM_CHECK(options.Check(), "AssociateByTime: invalid options (max_diff_s ", options.max_diff_s,
                 ", est_offset_s ", options.est_offset_s, ")");
  FLATSLAM_CHECK(!gt.empty(), "AssociateByTime: the ground truth has no poses");
  FLATSLAM_CHECK(!est.empty(), "AssociateByTime: the estimate has no poses");
  const int64_t max_diff_ns = SecondsToNs(options.max_diff_s);
  const int64_t offset_ns = SecondsToNs(options.est_offset_s);
  // evo: the estimate is the shorter one unless the ground truth is strictly shorter.
  const bool est_is_short = est.size() <= gt.size();
  const Trajectory& short_traj = est_is_short ? est : gt;
  const Trajectory& long_traj = est_is_short ? gt : est;
  const int64_t short_offset = est_is_short ? offset_ns : 0;
  const int64_t long_offset = est_is_short ? 0 : offset_ns;

  // Long timestamps sorted, stable so that equal times keep file order (argmin takes the first).
  std::vector<std::pair<int64_t, size_t>> sorted(long_traj.size());
  for (size_t k = 0; k < long_traj.size(); ++k) sorted[k] = {long_traj[k].t_ns + long_offset, k};
  std::stable_sort(sorted.begin(), sorted.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  auto first_with_time = [&](int64_t t) {
    return std::lower_bound(sorted.begin(), sorted.end(), t,
                            [](const auto& entry, int64_t value) { return entry.first < value; });
  };

  std::vector<IndexPair> pairs;
  for (size_t s = 0; s < short_traj.size(); ++s) {
    const int64_t t = short_traj[s].t_ns + short_offset;
    auto hi = first_with_time(t);
    std::optional<std::pair<int64_t, size_t>> best;  // (|dt|, long index)
    auto consider = [&](int64_t candidate_time) {
      const size_t index = first_with_time(candidate_time)->second;
      const int64_t dt = candidate_time > t ? candidate_time - t : t - candidate_time;
      if (!best || dt < best->first || (dt == best->first && index < best->second)) best = {{dt, index}};
    };
    if (hi != sorted.end()) consider(hi->first);
    if (hi != sorted.begin()) consider(std::prev(hi)->first);
    if (best && best->first <= max_diff_ns) {
      pairs.push_back(est_is_short ? IndexPair{best->second, s} : IndexPair{s, best->second});
    }
  }
  return pairs;
}

std::vector<IndexPair> AssociateByIndex(const Trajectory& gt, const Trajectory& est) {
  FLATSLAM_CHECK(gt.size() == est.size(), "cannot pair poses by index: the ground truth has ", gt.size(),
                 " poses and the estimate ", est.size());
  std::vector<IndexPair> pairs(gt.size());
  for (size_t i = 0; i < gt.size(); ++i) pairs[i] = {i, i};
  return pairs;
}

const char* AlignmentName(Alignment alignment) {
  switch (alignment) {
    case Alignment::kNone:
      return "none";
    case Alignment::kSE3:
      return "se3";
    case Alignment::kSim3:
      return "sim3";
  }
  return "?";
}

std::optional<Alignment> ParseAlignment(std::string_view name) {
  for (auto a : {Alignment::kNone, Alignment::kSE3, Alignment::kSim3}) {
    if (name == AlignmentName(a)) return a;
  }
  return std::nullopt;
}

Eigen::Isometry3d AlignmentResult::Apply(const Eigen::Isometry3d& T_world_cam) const {
  Eigen::Isometry3d out = Eigen::Isometry3d::Identity();
  out.linear() = rotation * T_world_cam.linear();
  out.translation() = scale * (rotation * T_world_cam.translation()) + translation;
  return out;
}

AlignmentResult AlignUmeyama(const std::vector<Eigen::Vector3d>& gt_positions,
                             const std::vector<Eigen::Vector3d>& est_positions, Alignment alignment) {
  FLATSLAM_CHECK(gt_positions.size() == est_positions.size(), "AlignUmeyama: ", gt_positions.size(),
                 " ground-truth positions but ", est_positions.size(), " estimated");
  AlignmentResult result;
  if (alignment == Alignment::kNone) return result;
  const auto n = static_cast<Eigen::Index>(gt_positions.size());
  Eigen::Matrix3Xd src(3, n), dst(3, n);
  for (Eigen::Index i = 0; i < n; ++i) {
    src.col(i) = est_positions[static_cast<size_t>(i)];
    dst.col(i) = gt_positions[static_cast<size_t>(i)];
  }
  const double spread = n > 0 ? (src.colwise() - src.rowwise().mean()).squaredNorm() : 0.0;
  // Without spread the scale is 0/0; a single point fixes no rotation either way.
  if (n < 1 || (alignment == Alignment::kSim3 && !(spread > 0))) {
    result.valid = false;
    return result;
  }
  const Eigen::Matrix4d sim = Eigen::umeyama(src, dst, alignment == Alignment::kSim3);
  if (!sim.allFinite()) {
    result.valid = false;
    return result;
  }
  const Eigen::Matrix3d scaled_rotation = sim.topLeftCorner<3, 3>();
  result.scale = alignment == Alignment::kSim3 ? std::cbrt(scaled_rotation.determinant()) : 1.0;
  result.rotation = scaled_rotation / result.scale;
  result.translation = sim.block<3, 1>(0, 3);
  result.valid = std::isfinite(result.scale) && result.scale > 0;
  if (!result.valid) result = AlignmentResult{.valid = false};
  return result;
}

ErrorStats ComputeErrorStats(std::vector<double> errors) {
  ErrorStats stats;
  stats.count = errors.size();
  if (errors.empty()) return stats;
  const double n = static_cast<double>(errors.size());
  double sum = 0, sum_sq = 0;
  for (double e : errors) {
    sum += e;
    sum_sq += e * e;
  }
  stats.mean = sum / n;
  stats.rmse = std::sqrt(sum_sq / n);
  double var = 0;
  for (double e : errors) var += (e - stats.mean) * (e - stats.mean);
  stats.std = std::sqrt(var / n);
  std::sort(errors.begin(), errors.end());
  stats.min = errors.front();
  stats.max = errors.back();
  const size_t mid = errors.size() / 2;
  stats.median = errors.size() % 2 == 1 ? errors[mid] : 0.5 * (errors[mid - 1] + errors[mid]);
  return stats;
}

ErrorStats ComputeAte(const std::vector<Eigen::Isometry3d>& gt, const std::vector<Eigen::Isometry3d>& est) {
  CheckSameLength(gt, est, "ATE");
  std::vector<double> errors(gt.size());
  for (size_t i = 0; i < gt.size(); ++i) errors[i] = (gt[i].translation() - est[i].translation()).norm();
  return ComputeErrorStats(std::move(errors));
}

RpeResult ComputeRpeFrames(const std::vector<Eigen::Isometry3d>& gt, const std::vector<Eigen::Isometry3d>& est,
                           size_t delta_frames) {
  CheckSameLength(gt, est, "RPE");
  FLATSLAM_CHECK(delta_frames >= 1, "RPE: the frame delta must be at least 1");
  std::vector<std::pair<size_t, size_t>> ids;
  for (size_t i = 0; i + delta_frames < gt.size(); i += delta_frames) ids.emplace_back(i, i + delta_frames);
  return RpeFromPairs(gt, est, ids);
}

RpeResult ComputeRpeDistance(const std::vector<Eigen::Isometry3d>& gt, const std::vector<Eigen::Isometry3d>& est,
                             double delta_m) {
  CheckSameLength(gt, est, "RPE");
  FLATSLAM_CHECK(std::isfinite(delta_m) && delta_m > 0, "RPE: the distance delta must be positive, got ", delta_m);
  const std::vector<double> dist = PathDistances(gt);
  std::vector<std::pair<size_t, size_t>> ids;
  size_t i = 0;
  for (size_t j = 1; j < gt.size(); ++j) {
    if (dist[j] - dist[i] >= delta_m) {
      ids.emplace_back(i, j);
      i = j;
    }
  }
  return RpeFromPairs(gt, est, ids);
}

bool KittiMetricOptions::Check() const {
  return step_frames >= 1 && !lengths_m.empty() &&
         std::all_of(lengths_m.begin(), lengths_m.end(), [](double l) { return std::isfinite(l) && l > 0; });
}

KittiMetricResult ComputeKittiMetric(const std::vector<Eigen::Isometry3d>& gt,
                                     const std::vector<Eigen::Isometry3d>& est, const KittiMetricOptions& options) {
  CheckSameLength(gt, est, "KITTI metric");
  FLATSLAM_CHECK(options.Check(), "KITTI metric: invalid options (lengths must be positive, step at least 1)");
  KittiMetricResult result;
  if (gt.empty()) return result;
  const std::vector<double> dist = PathDistances(gt);
  result.path_length_m = dist.back();
  double t_sum = 0, r_sum = 0;
  for (size_t first = 0; first < gt.size(); first += options.step_frames) {
    for (double length : options.lengths_m) {
      // First frame strictly further than `length` along the path (devkit lastFrameFromSegmentLength).
      auto it = std::upper_bound(dist.begin() + static_cast<std::ptrdiff_t>(first), dist.end(), dist[first] + length);
      if (it == dist.end()) continue;
      const auto last = static_cast<size_t>(it - dist.begin());
      const Eigen::Matrix4d error = Relative(est[first], est[last]).inverse() * Relative(gt[first], gt[last]);
      t_sum += error.block<3, 1>(0, 3).norm() / length;
      r_sum += RotationAngle(error.topLeftCorner<3, 3>()) / length;
      ++result.segments;
    }
  }
  if (result.segments == 0) return result;
  result.available = true;
  const double n = static_cast<double>(result.segments);
  result.t_rel_percent = 100.0 * t_sum / n;
  result.r_rel_deg_per_100m = 100.0 * kRadToDeg * r_sum / n;
  return result;
}

double RotationAngle(const Eigen::Matrix3d& r) {
  // sin from the skew part, cos from the trace: well conditioned at every angle.
  const Eigen::Vector3d axis_sin(r(2, 1) - r(1, 2), r(0, 2) - r(2, 0), r(1, 0) - r(0, 1));
  const double cos_angle = 0.5 * (r.trace() - 1.0);
  return std::atan2(0.5 * axis_sin.norm(), cos_angle);
}

bool EvalOptions::Check() const {
  return association.Check() && rpe_delta_frames >= 1 && std::isfinite(rpe_delta_m) && rpe_delta_m >= 0 &&
         kitti.Check();
}

EvalResult Evaluate(const Trajectory& gt, const Trajectory& est, const EvalOptions& options) {
  FLATSLAM_CHECK(options.Check(), "Evaluate: invalid options");
  FLATSLAM_CHECK(!gt.empty(), "the ground truth has no poses");
  FLATSLAM_CHECK(!est.empty(), "the estimate has no poses");
  EvalResult result;
  result.pairs = options.pair_by_index ? AssociateByIndex(gt, est) : AssociateByTime(gt, est, options.association);
  if (result.pairs.empty()) {
    Fail("no pose pairs: no timestamp of the estimate (", FormatNsAsSeconds(est.front().t_ns), " .. ",
         FormatNsAsSeconds(est.back().t_ns), " s) is within ", options.association.max_diff_s,
         " s of one of the ground truth (", FormatNsAsSeconds(gt.front().t_ns), " .. ",
         FormatNsAsSeconds(gt.back().t_ns), " s)");
  }
  std::vector<Eigen::Isometry3d> gt_poses, est_poses;
  std::vector<Eigen::Vector3d> gt_positions, est_positions;
  for (const IndexPair& p : result.pairs) {
    gt_poses.push_back(gt[p.gt_index].T_world_cam);
    est_poses.push_back(est[p.est_index].T_world_cam);
    gt_positions.push_back(gt_poses.back().translation());
    est_positions.push_back(est_poses.back().translation());
  }
  result.alignment = AlignUmeyama(gt_positions, est_positions, options.alignment);
  FLATSLAM_CHECK(result.alignment.valid, "cannot align the estimate (", AlignmentName(options.alignment), ") on ",
                 result.pairs.size(), " pose pairs: its positions do not spread; try --align none");
  for (Eigen::Isometry3d& pose : est_poses) pose = result.alignment.Apply(pose);
  result.ate_m = ComputeAte(gt_poses, est_poses);
  result.rpe_frames = ComputeRpeFrames(gt_poses, est_poses, options.rpe_delta_frames);
  if (options.rpe_delta_m > 0) result.rpe_distance = ComputeRpeDistance(gt_poses, est_poses, options.rpe_delta_m);
  result.kitti = ComputeKittiMetric(gt_poses, est_poses, options.kitti);
  return result;
}

JointAteResult EvaluateJointAte(const std::vector<Trajectory>& gt, const std::vector<Trajectory>& est,
                                const EvalOptions& options) {
  FLATSLAM_CHECK(options.Check(), "EvaluateJointAte: invalid options");
  FLATSLAM_CHECK(gt.size() == est.size() && !gt.empty(), "joint ATE: one ground truth per estimate");
  JointAteResult result;
  std::vector<std::vector<Eigen::Isometry3d>> gt_poses(gt.size()), est_poses(gt.size());
  std::vector<Eigen::Vector3d> gt_positions, est_positions;
  for (size_t k = 0; k < gt.size(); ++k) {
    const std::vector<IndexPair> pairs =
        options.pair_by_index ? AssociateByIndex(gt[k], est[k]) : AssociateByTime(gt[k], est[k], options.association);
    FLATSLAM_CHECK(!pairs.empty(), "estimate ", k + 1, " has no pose paired with its ground truth");
    std::vector<Eigen::Vector3d> own_gt, own_est;
    for (const IndexPair& p : pairs) {
      gt_poses[k].push_back(gt[k][p.gt_index].T_world_cam);
      est_poses[k].push_back(est[k][p.est_index].T_world_cam);
      own_gt.push_back(gt_poses[k].back().translation());
      own_est.push_back(est_poses[k].back().translation());
    }
    gt_positions.insert(gt_positions.end(), own_gt.begin(), own_gt.end());
    est_positions.insert(est_positions.end(), own_est.begin(), own_est.end());
    result.pairs.push_back(pairs.size());
    // Aligned alone (none when its positions do not spread: count 0).
    const AlignmentResult own = AlignUmeyama(own_gt, own_est, options.alignment);
    std::vector<Eigen::Isometry3d> aligned = est_poses[k];
    for (Eigen::Isometry3d& pose : aligned) pose = own.Apply(pose);
    result.own_ate_m.push_back(own.valid ? ComputeAte(gt_poses[k], aligned) : ErrorStats{});
  }
  result.alignment = AlignUmeyama(gt_positions, est_positions, options.alignment);
  FLATSLAM_CHECK(result.alignment.valid, "cannot align the estimates together (", AlignmentName(options.alignment),
                 ") on ", gt_positions.size(), " pose pairs: their positions do not spread");
  std::vector<Eigen::Isometry3d> all_gt, all_est;
  for (size_t k = 0; k < gt.size(); ++k) {
    for (Eigen::Isometry3d& pose : est_poses[k]) pose = result.alignment.Apply(pose);
    result.ate_m.push_back(ComputeAte(gt_poses[k], est_poses[k]));
    all_gt.insert(all_gt.end(), gt_poses[k].begin(), gt_poses[k].end());
    all_est.insert(all_est.end(), est_poses[k].begin(), est_poses[k].end());
  }
  result.all_m = ComputeAte(all_gt, all_est);
  return result;
}

}  // namespace flatslam
