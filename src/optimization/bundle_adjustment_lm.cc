// The hand-written bundle adjustment solver: Levenberg-Marquardt on the reduced camera system.
// Points are eliminated per point (3x3 blocks), the pose system is solved densely when small and
// with a sparse LDLT otherwise. Structure is analysed once per pass; an iteration is a pass over
// the observations plus one factorization, with no per-iteration allocation. The iterative Schur
// variant replaces the factorization by preconditioned conjugate gradients on the same system,
// kept implicit: only its diagonal blocks are formed, and each product passes over the
// observations' pose-point blocks, so memory follows the observations, not the pairs of poses
// that share points (a whole merged map has some 175,000 such pairs). Passes over the points run
// on TBB over fixed slices (see kSlices): a slice sums its points' terms into blocks of its own.
#include "optimization/bundle_adjustment_lm.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <optional>
#include <unordered_map>
#include <utility>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>
#include <Eigen/Cholesky>
#include <Eigen/SparseCholesky>

#include "core/cpu_features.h"
#include "optimization/inverse_depth.h"
#include "optimization/lm_terms.h"

namespace flatslam::detail {

struct PoseState {
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
};

namespace {

constexpr double kMinDiagonal = 1e-6;  // lower clamp of the LM scaling diagonal (as Ceres)
constexpr double kMaxDiagonal = 1e32;
// Linearization and elimination split their passes over the points into this many fixed slices,
// whatever the number of threads: the sums they make in slice order do not depend on it.
constexpr size_t kSlices = 8;
// Points per task of the passes over points that sum nothing across points.
constexpr size_t kPointGrain = 64;

using Mat6 = Eigen::Matrix<double, 6, 6>;
using Mat63 = Eigen::Matrix<double, 6, 3>;
using Vec6 = Eigen::Matrix<double, 6, 1>;

}  // namespace

void SchurProductSlice(const uint32_t* obs_start, const int* obs_free, const double* W, const Eigen::Matrix3d* V_inv,
                       const double* p, double* partial, size_t j0, size_t j1) {
  using ConstVec6Map = Eigen::Map<const Eigen::Matrix<double, 6, 1>>;
  for (size_t j = j0; j < j1; ++j) {
    Eigen::Vector3d t = Eigen::Vector3d::Zero();
    for (uint32_t a = obs_start[j]; a < obs_start[j + 1]; ++a)
      if (obs_free[a] >= 0)
        t.noalias() += Eigen::Map<const Mat63>(W + 18 * a).transpose() * ConstVec6Map(p + 6 * obs_free[a]);
    const Eigen::Vector3d u = V_inv[j] * t;
    for (uint32_t a = obs_start[j]; a < obs_start[j + 1]; ++a)
      if (obs_free[a] >= 0)
        Eigen::Map<Vec6>(partial + 6 * obs_free[a]).noalias() -= Eigen::Map<const Mat63>(W + 18 * a) * u;
  }
}

#if defined(__x86_64__)
namespace {
__attribute__((target("avx2,fma"))) inline double Sum(__m256d a, __m128d b) {
  const __m128d s = _mm_add_pd(_mm_add_pd(_mm256_castpd256_pd128(a), _mm256_extractf128_pd(a, 1)), b);
  return _mm_cvtsd_f64(_mm_add_sd(s, _mm_unpackhi_pd(s, s)));
}
}  // namespace

// Each 6-vector in a 4-lane and a 2-lane register; t's lanes summed once per point.
__attribute__((target("avx2,fma"))) void SchurProductSliceAvx2(const uint32_t* obs_start, const int* obs_free,
                                                               const double* W, const Eigen::Matrix3d* V_inv,
                                                               const double* p, double* partial, size_t j0, size_t j1) {
  for (size_t j = j0; j < j1; ++j) {
    __m256d t0 = _mm256_setzero_pd(), t1 = t0, t2 = t0;
    __m128d s0 = _mm_setzero_pd(), s1 = s0, s2 = s0;
    for (uint32_t a = obs_start[j]; a < obs_start[j + 1]; ++a) {
      if (obs_free[a] < 0) continue;
      const double* w = W + 18 * a;
      const double* x = p + 6 * obs_free[a];
      const __m256d x4 = _mm256_loadu_pd(x);
      const __m128d x2 = _mm_loadu_pd(x + 4);
      t0 = _mm256_fmadd_pd(_mm256_loadu_pd(w), x4, t0);
      s0 = _mm_fmadd_pd(_mm_loadu_pd(w + 4), x2, s0);
      t1 = _mm256_fmadd_pd(_mm256_loadu_pd(w + 6), x4, t1);
      s1 = _mm_fmadd_pd(_mm_loadu_pd(w + 10), x2, s1);
      t2 = _mm256_fmadd_pd(_mm256_loadu_pd(w + 12), x4, t2);
      s2 = _mm_fmadd_pd(_mm_loadu_pd(w + 16), x2, s2);
    }
    const Eigen::Vector3d u = V_inv[j] * Eigen::Vector3d(Sum(t0, s0), Sum(t1, s1), Sum(t2, s2));
    const __m256d u0 = _mm256_set1_pd(u.x()), u1 = _mm256_set1_pd(u.y()), u2 = _mm256_set1_pd(u.z());
    for (uint32_t a = obs_start[j]; a < obs_start[j + 1]; ++a) {
      if (obs_free[a] < 0) continue;
      const double* w = W + 18 * a;
      double* y = partial + 6 * obs_free[a];
      __m256d y4 = _mm256_loadu_pd(y);
      __m128d y2 = _mm_loadu_pd(y + 4);
      y4 = _mm256_fnmadd_pd(_mm256_loadu_pd(w), u0, y4);
      y2 = _mm_fnmadd_pd(_mm_loadu_pd(w + 4), _mm256_castpd256_pd128(u0), y2);
      y4 = _mm256_fnmadd_pd(_mm256_loadu_pd(w + 6), u1, y4);
      y2 = _mm_fnmadd_pd(_mm_loadu_pd(w + 10), _mm256_castpd256_pd128(u1), y2);
      y4 = _mm256_fnmadd_pd(_mm256_loadu_pd(w + 12), u2, y4);
      y2 = _mm_fnmadd_pd(_mm_loadu_pd(w + 16), _mm256_castpd256_pd128(u2), y2);
      _mm256_storeu_pd(y, y4);
      _mm_storeu_pd(y + 4, y2);
    }
  }
}
#endif

void SubtractBlockProduct(double* S, const double* A, const double* B) {
  Eigen::Map<Mat6>(S).noalias() -= Eigen::Map<const Mat63>(A) * Eigen::Map<const Mat63>(B).transpose();
}

#if defined(__x86_64__)
// Column c of S: rows 0-3 in one register, rows 4-5 in another; A's columns loaded once.
__attribute__((target("avx2"))) void SubtractBlockProductAvx(double* S, const double* A, const double* B) {
  const __m256d a0 = _mm256_loadu_pd(A), a1 = _mm256_loadu_pd(A + 6), a2 = _mm256_loadu_pd(A + 12);
  const __m128d c0 = _mm_loadu_pd(A + 4), c1 = _mm_loadu_pd(A + 10), c2 = _mm_loadu_pd(A + 16);
  for (int c = 0; c < 6; ++c) {
    const __m256d b0 = _mm256_broadcast_sd(B + c), b1 = _mm256_broadcast_sd(B + 6 + c),
                  b2 = _mm256_broadcast_sd(B + 12 + c);
    const __m256d top =
        _mm256_add_pd(_mm256_add_pd(_mm256_mul_pd(a0, b0), _mm256_mul_pd(a1, b1)), _mm256_mul_pd(a2, b2));
    const __m128d bottom =
        _mm_add_pd(_mm_add_pd(_mm_mul_pd(c0, _mm256_castpd256_pd128(b0)), _mm_mul_pd(c1, _mm256_castpd256_pd128(b1))),
                   _mm_mul_pd(c2, _mm256_castpd256_pd128(b2)));
    double* s = S + 6 * c;
    _mm256_storeu_pd(s, _mm256_sub_pd(_mm256_loadu_pd(s), top));
    _mm_storeu_pd(s + 4, _mm_sub_pd(_mm_loadu_pd(s + 4), bottom));
  }
}
#endif

// Buffers of one solve, kept between solves so that their capacity is reused.
struct SchurWorkspace {
  std::vector<int> free_id, point_id;
  std::vector<uint32_t> free_poses, points;  // free pose -> problem pose, point id -> problem point
  std::vector<uint32_t> obs_start, obs;      // observations by point (CSR over point ids)
  std::vector<int> obs_free;                 // free pose of each of obs, -1 if fixed
  std::vector<uint32_t> fill;
  std::vector<uint32_t> block_rows, block_cols, pair_blocks;
  std::unordered_map<uint64_t, uint32_t> block_of;
  std::vector<Mat6, Eigen::aligned_allocator<Mat6>> blocks, U, U_damped;
  std::vector<Mat63, Eigen::aligned_allocator<Mat63>> W;
  std::vector<Eigen::Matrix3d> V, V_inv;
  std::vector<Eigen::Vector3d> b_point, delta_point;
  std::vector<Vec6, Eigen::aligned_allocator<Vec6>> b_pose, delta_pose, g;
  std::vector<Mat6, Eigen::aligned_allocator<Mat6>> block_inv;               // conjugate gradients:
  std::vector<Vec6, Eigen::aligned_allocator<Vec6>> cg_r, cg_z, cg_p, cg_q;  // preconditioner, vectors
  // Conjugate gradients' products: one partial product per fixed slice of the points, summed in
  // slice order, so the result does not depend on how many threads ran the slices.
  std::vector<std::vector<Vec6, Eigen::aligned_allocator<Vec6>>> cg_partial;
  std::vector<PoseState> state, trial_poses;
  // Points by solver id (optimization/inverse_depth.h): parameters (inverse depth or world
  // coordinates), trial parameters, anchors.
  std::vector<Eigen::Vector3d> theta, trial_theta;
  std::vector<InverseDepthAnchor> anchors;
  std::vector<uint8_t> unanchored;                        // behind every camera that observes it: it stays where it is
  std::vector<uint8_t> euclidean;                         // adjusted in world coordinates (theta = X, rho = 1)
  std::vector<uint32_t> pair_start;  // by point: its first entry of pair_blocks
  std::vector<double> obs_rho;       // cost, by observation (summed in observation order)
  // By fixed slice of the points: the sums of its points' terms, added up in slice order.
  struct Slice {
    // Linearization: the pose blocks U and b.
    std::vector<Mat6, Eigen::aligned_allocator<Mat6>> U;
    std::vector<Vec6, Eigen::aligned_allocator<Vec6>> b;
    // Elimination: what its points take from the reduced camera system's blocks and right-hand
    // side, and one point's W V^-1 and free observations.
    std::vector<Mat6, Eigen::aligned_allocator<Mat6>> blocks;
    std::vector<Vec6, Eigen::aligned_allocator<Vec6>> g;
    std::vector<Mat63, Eigen::aligned_allocator<Mat63>> Y;
    std::vector<uint32_t> free_obs;
  };
  std::vector<Slice> slices;
};

namespace {

class Solver {
 public:
  Solver(const BundleAdjustmentProblem& input, const BundleAdjustmentOptions& options,
         const std::vector<uint8_t>& active, bool robust, bool dense, SchurWorkspace* w)
      : in_(input),
        options_(options),
        robust_(robust),
        dense_(dense),
        iterative_(options.linear_solver == BundleAdjustmentOptions::LinearSolver::kIterativeSchur),
        bf_(input.camera.fx * input.baseline_m),
        w_(*w) {
    // 0: the calling arena's threads (its limits hold); n > 1: an arena of its own.
    parallel_ = options.schur_lm_threads != 1;
    if (options.schur_lm_threads > 1) arena_.emplace(options.schur_lm_threads);
    w_.free_poses.clear();
    w_.points.clear();
    w_.block_rows.clear();
    w_.block_cols.clear();
    w_.pair_blocks.clear();
    // Free poses and points that take part, observations grouped by point.
    w_.free_id.assign(input.poses.size(), -1);
    w_.point_id.assign(input.points.size(), -1);
    for (size_t i = 0; i < input.observations.size(); ++i) {
      if (!active[i]) continue;
      const BundleAdjustmentObservation& o = input.observations[i];
      if (w_.point_id[o.point_index] < 0) {
        w_.point_id[o.point_index] = static_cast<int>(w_.points.size());
        w_.points.push_back(o.point_index);
      }
      if (!input.poses[o.pose_index].fixed && w_.free_id[o.pose_index] < 0) {
        w_.free_id[o.pose_index] = static_cast<int>(w_.free_poses.size());
        w_.free_poses.push_back(o.pose_index);
      }
    }
    w_.obs_start.assign(w_.points.size() + 1, 0);
    for (size_t i = 0; i < input.observations.size(); ++i)
      if (active[i]) ++w_.obs_start[w_.point_id[input.observations[i].point_index] + 1];
    for (size_t j = 0; j < w_.points.size(); ++j) w_.obs_start[j + 1] += w_.obs_start[j];
    w_.obs.resize(w_.obs_start.back());
    {
      std::vector<uint32_t>& fill = w_.fill;
      fill.assign(w_.obs_start.begin(), w_.obs_start.end() - 1);
      for (size_t i = 0; i < input.observations.size(); ++i)
        if (active[i]) w_.obs[fill[w_.point_id[input.observations[i].point_index]]++] = static_cast<uint32_t>(i);
    }
    w_.obs_free.resize(w_.obs.size());
    for (size_t a = 0; a < w_.obs.size(); ++a) w_.obs_free[a] = w_.free_id[input.observations[w_.obs[a]].pose_index];
    // Blocks of the reduced camera system: the diagonal, then every pair of free poses that
    // share a point, in the order the elimination visits them.
    const size_t nf = w_.free_poses.size();
    std::unordered_map<uint64_t, uint32_t>& block_of = w_.block_of;
    block_of.clear();
    auto block = [&](uint32_t a, uint32_t b) {
      const uint64_t key = (static_cast<uint64_t>(a) << 32) | b;
      const auto [it, inserted] = block_of.try_emplace(key, static_cast<uint32_t>(w_.block_rows.size()));
      if (inserted) {
        w_.block_rows.push_back(a);
        w_.block_cols.push_back(b);
      }
      return it->second;
    };
    for (uint32_t f = 0; f < nf; ++f) block(f, f);
    // Conjugate gradients keep the off-diagonal blocks implicit (see ConjugateGradients).
    w_.pair_start.assign(w_.points.size() + 1, 0);
    for (size_t j = 0; j < (iterative_ ? 0 : w_.points.size()); ++j) {
      w_.pair_start[j] = static_cast<uint32_t>(w_.pair_blocks.size());
      for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a) {
        const int fa = w_.free_id[input.observations[w_.obs[a]].pose_index];
        if (fa < 0) continue;
        for (uint32_t b = a + 1; b < w_.obs_start[j + 1]; ++b) {
          const int fb = w_.free_id[input.observations[w_.obs[b]].pose_index];
          if (fb < 0 || fb == fa) continue;
          w_.pair_blocks.push_back(block(std::min(fa, fb), std::max(fa, fb)));
        }
      }
    }
    if (!iterative_) w_.pair_start[w_.points.size()] = static_cast<uint32_t>(w_.pair_blocks.size());
    w_.blocks.resize(w_.block_rows.size());
    w_.W.resize(w_.obs.size());
    w_.V.resize(w_.points.size());
    w_.b_point.resize(w_.points.size());
    w_.U.resize(nf);
    w_.b_pose.resize(nf);
    w_.delta_pose.resize(nf);
    w_.delta_point.resize(w_.points.size());
  }

  // Runs up to `iterations` LM iterations on poses/points; returns false on numerical failure.
  bool Run(std::vector<PoseState>* poses, std::vector<Eigen::Vector3d>* points, int iterations, int* iterations_done,
           bool* stopped) {
    if (w_.obs.empty()) return true;
    ToParameters(*poses, *points);
    std::vector<Eigen::Vector3d>& theta = w_.theta;
    double cost = 0;
    if (!Cost(*poses, theta, &cost)) return false;
    double radius = 1e4;  // trust region radius; the damping is 1 / radius (Ceres' defaults)
    double nu = 2;
    std::vector<PoseState>& trial_poses = w_.trial_poses;
    std::vector<Eigen::Vector3d>& trial_theta = w_.trial_theta;
    trial_poses = *poses;
    trial_theta = theta;
    bool linearized = false;  // the normal equations are those of the current estimate
    for (int it = 0; it < iterations; ++it) {
      ++*iterations_done;
      // A rejected step leaves the estimate as it was: only the damping changes, so the blocks
      // of the last linearization still hold.
      if (!linearized) Linearize(*poses, theta);
      linearized = true;
      const double lambda = 1.0 / radius;
      bool solved = Solve(lambda);
      double trial_cost = std::numeric_limits<double>::infinity();
      if (solved) {
        for (size_t f = 0; f < w_.free_poses.size(); ++f) {
          const uint32_t k = w_.free_poses[f];
          const Eigen::Matrix3d dR = ExpSo3(w_.delta_pose[f].head<3>());
          trial_poses[k].R = dR * (*poses)[k].R;
          trial_poses[k].t = dR * (*poses)[k].t + w_.delta_pose[f].tail<3>();
        }
        for (size_t j = 0; j < w_.points.size(); ++j) trial_theta[j] = theta[j] + w_.delta_point[j];
        solved = Cost(trial_poses, trial_theta, &trial_cost);
      }
      // Gain ratio against the decrease the damped linear model predicts.
      const double predicted = solved ? PredictedDecrease(lambda) : 0;
      const double gain = predicted > 0 ? (cost - trial_cost) / predicted : -1;
      if (solved && gain > 0 && std::isfinite(trial_cost)) {
        const double relative_decrease = (cost - trial_cost) / std::max(cost, 1e-300);
        for (size_t f = 0; f < w_.free_poses.size(); ++f) (*poses)[w_.free_poses[f]] = trial_poses[w_.free_poses[f]];
        theta.swap(trial_theta);
        trial_theta = theta;
        cost = trial_cost;
        linearized = false;
        radius /= std::max(1.0 / 3.0, 1.0 - std::pow(2.0 * gain - 1.0, 3));
        radius = std::min(radius, 1e16);
        nu = 2;
        if (relative_decrease < 1e-6) break;  // converged (Ceres' function tolerance)
      } else {
        radius /= nu;
        nu *= 2;
        if (radius < 1e-32) break;
      }
      if (options_.stop_early && options_.stop_early()) {
        *stopped = true;
        break;
      }
    }
    FromParameters(points);
    return true;
  }

 private:
  // Points are adjusted in inverse depth (optimization/inverse_depth.h) as
  // options.inverse_depth_points asks, else in world coordinates. An inverse-depth point is
  // anchored in the first camera that sees it in front as the pass begins. Every active
  // observation does when a factorizing pass begins; the iterative one may start with points
  // behind all their cameras, which keep their place and count as outliers.
  void ToParameters(const std::vector<PoseState>& poses, const std::vector<Eigen::Vector3d>& points) {
    const size_t n = w_.points.size();
    w_.theta.resize(n);
    w_.anchors.resize(n);
    w_.unanchored.assign(n, 0);
    w_.euclidean.assign(n, 0);
    for (size_t j = 0; j < n; ++j) {
      const Eigen::Vector3d& X = points[w_.points[j]];
      bool measured_depth = false;
      if (options_.inverse_depth_points == 1)
        for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a)
          measured_depth = measured_depth || in_.observations[w_.obs[a]].right_u >= 0;
      if (!InInverseDepth(options_.inverse_depth_points, measured_depth)) {
        w_.euclidean[j] = 1;
        w_.theta[j] = X;
        continue;
      }
      w_.unanchored[j] = 1;
      w_.theta[j] = Eigen::Vector3d(0, 0, 1);
      w_.anchors[j] = InverseDepthAnchor::Of(poses[0].R, poses[0].t);
      for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a) {
        const PoseState& pose = poses[in_.observations[w_.obs[a]].pose_index];
        if ((pose.R * X + pose.t).z() <= kMinHomogeneousDepth) continue;
        w_.anchors[j] = InverseDepthAnchor::Of(pose.R, pose.t);
        w_.theta[j] = detail::ToInverseDepth(pose.R, pose.t, X);
        w_.unanchored[j] = 0;
        break;
      }
    }
  }

  // Back to world points; one the pass moved to or beyond infinity keeps the position it came with.
  void FromParameters(std::vector<Eigen::Vector3d>* points) const {
    for (size_t j = 0; j < w_.points.size(); ++j) {
      if (w_.euclidean[j])
        (*points)[w_.points[j]] = w_.theta[j];
      else if (!w_.unanchored[j])
        detail::FromInverseDepth(w_.anchors[j], w_.theta[j], &(*points)[w_.points[j]]);
    }
  }

  // Point j's homogeneous world point q and its rho from its parameters (a world point: q = X,
  // rho = 1).
  [[nodiscard]] Eigen::Vector3d Homogeneous(size_t j, const Eigen::Vector3d& theta, double* rho) const {
    *rho = w_.euclidean[j] ? 1.0 : theta.z();
    return w_.euclidean[j] ? theta : w_.anchors[j].Homogeneous(theta);
  }

  // Point j's reprojection in pose; false where it is behind the camera (or unanchored).
  template <int N>
  bool Residual(const PoseState& pose, size_t j, const Eigen::Vector3d& q, double rho,
                const BundleAdjustmentObservation& o, Eigen::Vector3d* h, Eigen::Matrix<double, N, 1>* r,
                Eigen::Matrix<double, N, 3>* J) const {
    if (w_.unanchored[j]) return false;
    return ReprojectHomogeneous<N>(in_.camera, bf_, pose.R, pose.t, q, rho, o.uv, o.right_u, h, r, J);
  }

  [[nodiscard]] double Delta(const BundleAdjustmentObservation& o) const {
    return o.right_u >= 0 ? options_.huber_stereo : options_.huber_mono;
  }

  // Half the robust cost, as Ceres reports it. A point behind a camera makes the state invalid
  // (false), except in the iterative solver: there the observation costs what one on the outlier
  // gate does, as the outlier it will be classified. A whole merged map starts far from its
  // minimum; its full steps put a few weakly constrained points behind a camera, and rejecting
  // each such step would stall the adjustment on them while every other point waits.
  bool Cost(const std::vector<PoseState>& poses, const std::vector<Eigen::Vector3d>& theta, double* cost) {
    std::atomic<bool> behind{false};
    w_.obs_rho.resize(w_.obs.size());
    ForRanges(w_.points.size(), [&](size_t j0, size_t j1) {
      for (size_t j = j0; j < j1; ++j) {
        double inv_depth = 0;
        const Eigen::Vector3d q = Homogeneous(j, theta[j], &inv_depth);
        for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a) {
          const BundleAdjustmentObservation& o = in_.observations[w_.obs[a]];
          Eigen::Vector3d h;
          double s = 0;
          bool in_front = true;
          if (o.right_u >= 0) {
            Eigen::Vector3d r;
            in_front = Residual<3>(poses[o.pose_index], j, q, inv_depth, o, &h, &r, nullptr);
            s = in_front ? r.squaredNorm() * o.inv_sigma2 : options_.chi2_stereo;
          } else {
            Eigen::Vector2d r;
            in_front = Residual<2>(poses[o.pose_index], j, q, inv_depth, o, &h, &r, nullptr);
            s = in_front ? r.squaredNorm() * o.inv_sigma2 : options_.chi2_mono;
          }
          if (!in_front && !iterative_) {
            behind = true;
            return;
          }
          double weight = 0;
          Huber(s, Delta(o), robust_, &w_.obs_rho[a], &weight);
        }
      }
    });
    if (behind) return false;
    double sum = 0;
    for (const double rho : w_.obs_rho) sum += rho;  // in observation order, as one pass sums
    *cost = 0.5 * sum;
    return std::isfinite(*cost);
  }

  // Accumulates one observation's normal-equation blocks.
  template <int N>
  void Accumulate(const PoseState& pose, size_t j, const Eigen::Vector3d& q, double inv_depth,
                  const BundleAdjustmentObservation& o, int free, Eigen::Matrix3d* V, Eigen::Vector3d* bl, uint32_t a,
                  Mat6* U, Vec6* b) {
    Eigen::Vector3d h;
    Eigen::Matrix<double, N, 1> r;
    Eigen::Matrix<double, N, 3> J;
    if (!Residual<N>(pose, j, q, inv_depth, o, &h, &r, &J)) {
      w_.W[a].setZero();
      return;
    }
    double rho = 0, weight = 0;
    Huber(r.squaredNorm() * o.inv_sigma2, Delta(o), robust_, &rho, &weight);
    const double w = weight * o.inv_sigma2;
    Eigen::Matrix<double, N, 3> Jl;
    Eigen::Matrix<double, N, 6> Jp;
    PointJacobians<N>(J, h, inv_depth, bf_, pose.R, pose.t, w_.euclidean[j] ? nullptr : &w_.anchors[j],
                      free < 0 ? nullptr : &Jp, &Jl);
    *V += w * Jl.transpose() * Jl;
    *bl += w * Jl.transpose() * r;
    if (free < 0) return;
    U[free].noalias() += w * Jp.transpose() * Jp;
    b[free].noalias() += w * Jp.transpose() * r;
    w_.W[a].noalias() = w * Jp.transpose() * Jl;
  }

  // Normal-equation blocks at the current estimate, over fixed slices of the points, each with its
  // own pose blocks summed in slice order (the same bits on any number of threads).
  void Linearize(const std::vector<PoseState>& poses, const std::vector<Eigen::Vector3d>& theta) {
    const size_t nf = w_.free_poses.size();
    w_.slices.resize(kSlices);
    RunSlices([&](size_t c) {
      SchurWorkspace::Slice& slice = w_.slices[c];
      slice.U.assign(nf, Mat6::Zero());
      slice.b.assign(nf, Vec6::Zero());
      const auto [j0, j1] = SlicePoints(c);
      LinearizePoints(poses, theta, j0, j1, slice.U.data(), slice.b.data());
    });
    for (size_t f = 0; f < nf; ++f) {
      w_.U[f] = w_.slices[0].U[f];
      w_.b_pose[f] = w_.slices[0].b[f];
      for (size_t c = 1; c < kSlices; ++c) {
        w_.U[f] += w_.slices[c].U[f];
        w_.b_pose[f] += w_.slices[c].b[f];
      }
    }
  }

  // Points [j0, j1): their blocks, and their observations' pose blocks added to U and b.
  void LinearizePoints(const std::vector<PoseState>& poses, const std::vector<Eigen::Vector3d>& theta, size_t j0,
                       size_t j1, Mat6* U, Vec6* b) {
    for (size_t j = j0; j < j1; ++j) {
      Eigen::Matrix3d V = Eigen::Matrix3d::Zero();
      Eigen::Vector3d bl = Eigen::Vector3d::Zero();
      double inv_depth = 0;
      const Eigen::Vector3d q = Homogeneous(j, theta[j], &inv_depth);
      for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a) {
        const BundleAdjustmentObservation& o = in_.observations[w_.obs[a]];
        const int free = w_.free_id[o.pose_index];
        if (o.right_u >= 0)
          Accumulate<3>(poses[o.pose_index], j, q, inv_depth, o, free, &V, &bl, a, U, b);
        else
          Accumulate<2>(poses[o.pose_index], j, q, inv_depth, o, free, &V, &bl, a, U, b);
      }
      w_.V[j] = V;
      w_.b_point[j] = bl;
    }
  }

  // The points [j0, j1) of fixed slice c.
  [[nodiscard]] std::pair<size_t, size_t> SlicePoints(size_t c) const {
    const size_t n = w_.points.size();
    return {n * c / kSlices, n * (c + 1) / kSlices};
  }

  // Runs slice(c) for c in [0, kSlices): on the solver's arena when it has one, else in order.
  template <class Slice>
  void RunSlices(const Slice& slice) {
    if (parallel_)
      Parallel([&] { tbb::parallel_for(size_t{0}, kSlices, slice); });
    else
      for (size_t c = 0; c < kSlices; ++c) slice(c);
  }

  // Runs body(j0, j1) over ranges covering the points [0, n): on the solver's threads when it has
  // them, else as one range. Callers make each point's result independent of the others.
  template <class Body>
  void ForRanges(size_t n, const Body& body) {
    if (parallel_ && n > kPointGrain)
      Parallel([&] {
        tbb::parallel_for(tbb::blocked_range<size_t>(0, n, kPointGrain),
                          [&](const tbb::blocked_range<size_t>& r) { body(r.begin(), r.end()); });
      });
    else if (n > 0)
      body(0, n);
  }

  // Runs f, which starts parallel work, on the solver's arena or the caller's, isolated: a thread
  // waiting for that work takes none of the arena's other tasks meanwhile (a tracking pipeline's
  // next frame, say), which would hold up the solve.
  template <class F>
  void Parallel(const F& f) {
    if (arena_)
      arena_->execute([&] { tbb::this_task_arena::isolate(f); });
    else
      tbb::this_task_arena::isolate(f);
  }

  // Points [j0, j1): each one's damped inverse (V_inv), and its terms W V^-1 W' and W V^-1 b
  // subtracted from the slice's blocks and right-hand side, each block's in the order the
  // elimination visits them. False if a point's block is not positive definite.
  bool EliminatePoints(double lambda, size_t j0, size_t j1, SchurWorkspace::Slice* slice) {
    static const auto subtract = [] {
#if defined(__x86_64__)
      if (HasAvx2()) return &SubtractBlockProductAvx;
#endif
      return &SubtractBlockProduct;
    }();
    std::vector<Mat6, Eigen::aligned_allocator<Mat6>>& blocks = slice->blocks;
    size_t pair = iterative_ ? 0 : w_.pair_start[j0];
    for (size_t j = j0; j < j1; ++j) {
      Eigen::Matrix3d V = w_.V[j];
      for (int d = 0; d < 3; ++d) V(d, d) += lambda * std::clamp(w_.V[j](d, d), kMinDiagonal, kMaxDiagonal);
      const Eigen::LDLT<Eigen::Matrix3d> ldlt(V);
      if (ldlt.info() != Eigen::Success || !ldlt.isPositive() || ldlt.vectorD().minCoeff() <= 0) return false;
      w_.V_inv[j] = ldlt.solve(Eigen::Matrix3d::Identity());
      const Eigen::Vector3d Vb = w_.V_inv[j] * w_.b_point[j];
      // The point's observations in free poses, each with its W V^-1.
      std::vector<uint32_t>& obs = slice->free_obs;
      obs.clear();
      for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a)
        if (w_.obs_free[a] >= 0) obs.push_back(a);
      slice->Y.resize(std::max(slice->Y.size(), obs.size()));
      for (size_t m = 0; m < obs.size(); ++m) {
        const Mat63& Wa = w_.W[obs[m]];
        slice->Y[m].noalias() = Wa * w_.V_inv[j];
        slice->g[w_.obs_free[obs[m]]].noalias() -= Wa * Vb;
      }
      // Every pair of them, in observation order.
      for (size_t m = 0; m < obs.size(); ++m) {
        const int fa = w_.obs_free[obs[m]];
        const Mat63& Y = slice->Y[m];
        subtract(blocks[fa].data(), Y.data(), w_.W[obs[m]].data());
        for (size_t l = m + 1; l < obs.size(); ++l) {
          const int fb = w_.obs_free[obs[l]];
          const Mat63& Wb = w_.W[obs[l]];
          if (fb == fa) {  // two observations in one keyframe: both cross terms on its diagonal
            blocks[fa].noalias() -= Y * Wb.transpose() + Wb * Y.transpose();
            continue;
          }
          if (iterative_) continue;
          // The block is stored once, as (min, max).
          if (fa < fb)
            subtract(blocks[w_.pair_blocks[pair]].data(), Y.data(), Wb.data());
          else
            subtract(blocks[w_.pair_blocks[pair]].data(), Wb.data(), Y.data());
          ++pair;
        }
      }
    }
    return true;
  }

  // Damped Schur complement, its solution and the back-substitution; false if not positive definite.
  // Each fixed slice of the points subtracts its terms from zeroed blocks of its own; the blocks
  // are then the damped pose blocks plus the slices' sums in slice order.
  bool Solve(double lambda) {
    const size_t nf = w_.free_poses.size();
    const size_t num_blocks = w_.blocks.size();
    w_.U_damped.resize(nf);
    for (size_t f = 0; f < nf; ++f) {
      Mat6& damped = w_.U_damped[f];
      damped = w_.U[f];
      for (int d = 0; d < 6; ++d) damped(d, d) += lambda * std::clamp(w_.U[f](d, d), kMinDiagonal, kMaxDiagonal);
    }
    w_.V_inv.resize(w_.points.size());
    w_.slices.resize(kSlices);
    std::atomic<bool> indefinite{false};
    RunSlices([&](size_t c) {
      SchurWorkspace::Slice& slice = w_.slices[c];
      slice.blocks.assign(num_blocks, Mat6::Zero());
      slice.g.assign(nf, Vec6::Zero());
      const auto [j0, j1] = SlicePoints(c);
      if (!EliminatePoints(lambda, j0, j1, &slice)) indefinite = true;
    });
    if (indefinite) return false;
    std::vector<Vec6, Eigen::aligned_allocator<Vec6>>& g = w_.g;
    g.assign(w_.b_pose.begin(), w_.b_pose.end());
    for (size_t k = 0; k < num_blocks; ++k) {
      w_.blocks[k] = k < nf ? w_.U_damped[k] : Mat6::Zero();
      for (size_t c = 0; c < kSlices; ++c) w_.blocks[k] += w_.slices[c].blocks[k];
    }
    for (size_t f = 0; f < nf; ++f)
      for (size_t c = 0; c < kSlices; ++c) g[f] += w_.slices[c].g[f];
    if (nf > 0 && iterative_) {
      if (!ConjugateGradients()) return false;
    } else if (nf > 0) {
      Eigen::VectorXd rhs(6 * nf), x;
      for (size_t f = 0; f < nf; ++f) rhs.segment<6>(6 * f) = g[f];
      if (dense_) {
        Eigen::MatrixXd S = Eigen::MatrixXd::Zero(6 * nf, 6 * nf);
        for (size_t k = 0; k < w_.blocks.size(); ++k)
          S.block<6, 6>(6 * w_.block_rows[k], 6 * w_.block_cols[k]) = w_.blocks[k];
        const Eigen::LLT<Eigen::MatrixXd, Eigen::Upper> llt(S);
        if (llt.info() != Eigen::Success) return false;
        x = llt.solve(rhs);
      } else {
        std::vector<Eigen::Triplet<double>> triplets;
        triplets.reserve(w_.blocks.size() * 36);
        for (size_t k = 0; k < w_.blocks.size(); ++k) {
          const bool diagonal = w_.block_rows[k] == w_.block_cols[k];
          for (int r = 0; r < 6; ++r)
            for (int c = diagonal ? r : 0; c < 6; ++c)
              triplets.emplace_back(6 * w_.block_rows[k] + r, 6 * w_.block_cols[k] + c, w_.blocks[k](r, c));
        }
        Eigen::SparseMatrix<double> S(6 * nf, 6 * nf);
        S.setFromTriplets(triplets.begin(), triplets.end());
        if (!sparse_analysed_) {
          sparse_.analyzePattern(S);
          sparse_analysed_ = true;
        }
        sparse_.factorize(S);
        if (sparse_.info() != Eigen::Success) return false;
        x = sparse_.solve(rhs);
      }
      if (!x.allFinite()) return false;
      for (size_t f = 0; f < nf; ++f) w_.delta_pose[f] = x.segment<6>(6 * f);
    }
    ForRanges(w_.points.size(), [&](size_t j0, size_t j1) {
      for (size_t j = j0; j < j1; ++j) {
        Eigen::Vector3d b = w_.b_point[j];
        for (uint32_t a = w_.obs_start[j]; a < w_.obs_start[j + 1]; ++a) {
          const int fa = w_.obs_free[a];
          if (fa >= 0) b.noalias() -= w_.W[a].transpose() * w_.delta_pose[fa];
        }
        w_.delta_point[j] = w_.V_inv[j] * b;
      }
    });
    gradient_dot_delta_ = 0;
    damping_term_ = 0;
    for (size_t f = 0; f < nf; ++f) {
      gradient_dot_delta_ += w_.b_pose[f].dot(w_.delta_pose[f]);
      for (int d = 0; d < 6; ++d)
        damping_term_ +=
            std::clamp(w_.U[f](d, d), kMinDiagonal, kMaxDiagonal) * w_.delta_pose[f](d) * w_.delta_pose[f](d);
    }
    for (size_t j = 0; j < w_.points.size(); ++j) {
      gradient_dot_delta_ += w_.b_point[j].dot(w_.delta_point[j]);
      for (int d = 0; d < 3; ++d)
        damping_term_ +=
            std::clamp(w_.V[j](d, d), kMinDiagonal, kMaxDiagonal) * w_.delta_point[j](d) * w_.delta_point[j](d);
    }
    return true;
  }

  // Solves the damped reduced camera system S = U_damped - W V^-1 W' (right-hand side w_.g) into
  // w_.delta_pose by conjugate gradients from zero, each step preconditioned by the inverse of
  // S's diagonal blocks (w_.blocks). S stays implicit: each product passes over the points. False
  // if a diagonal block is not positive definite or the iteration breaks down.
  bool ConjugateGradients() {
    const size_t nf = w_.free_poses.size();
    w_.block_inv.resize(nf);
    for (size_t f = 0; f < nf; ++f) {
      const Eigen::LLT<Mat6> llt(w_.blocks[f]);
      if (llt.info() != Eigen::Success) return false;
      w_.block_inv[f] = llt.solve(Mat6::Identity());
    }
    w_.cg_partial.resize(kSlices);
    for (auto& partial : w_.cg_partial) partial.resize(nf);
    auto& r = w_.cg_r;
    auto& z = w_.cg_z;
    auto& p = w_.cg_p;
    auto& q = w_.cg_q;
    auto& x = w_.delta_pose;
    r.assign(w_.g.begin(), w_.g.end());
    z.resize(nf);
    q.resize(nf);
    double rz = 0, rhs_norm2 = 0;
    for (size_t f = 0; f < nf; ++f) {
      x[f].setZero();
      z[f].noalias() = w_.block_inv[f] * r[f];
      rz += r[f].dot(z[f]);
      rhs_norm2 += r[f].squaredNorm();
    }
    p.assign(z.begin(), z.end());
    const double stop2 = kIterativeSchurTolerance * kIterativeSchurTolerance * rhs_norm2;
    // q = U_damped p - sum over points of W V^-1 W' p, the sum by slices of the points.
    static const auto product = [] {
#if defined(__x86_64__)
      if (HasAvx2Fma()) return &SchurProductSliceAvx2;
#endif
      return &SchurProductSlice;
    }();
    auto slice = [&](size_t c) {
      auto& partial = w_.cg_partial[c];
      for (Vec6& v : partial) v.setZero();
      const auto [j0, j1] = SlicePoints(c);
      product(w_.obs_start.data(), w_.obs_free.data(), w_.W.data()->data(), w_.V_inv.data(), p.data()->data(),
              partial.data()->data(), j0, j1);
    };
    for (int step = 0; step < kIterativeSchurMaxSteps && rhs_norm2 > 0; ++step) {
      RunSlices(slice);
      for (size_t f = 0; f < nf; ++f) {
        q[f].noalias() = w_.U_damped[f] * p[f];
        for (size_t c = 0; c < kSlices; ++c) q[f] += w_.cg_partial[c][f];
      }
      double pq = 0;
      for (size_t f = 0; f < nf; ++f) pq += p[f].dot(q[f]);
      if (!(pq > 0) || !std::isfinite(pq)) return step > 0;
      const double alpha = rz / pq;
      double r2 = 0, rz_next = 0;
      for (size_t f = 0; f < nf; ++f) {
        x[f].noalias() += alpha * p[f];
        r[f].noalias() -= alpha * q[f];
        r2 += r[f].squaredNorm();
        z[f].noalias() = w_.block_inv[f] * r[f];
        rz_next += r[f].dot(z[f]);
      }
      if (r2 <= stop2) break;
      const double beta = rz_next / rz;
      rz = rz_next;
      for (size_t f = 0; f < nf; ++f) p[f] = z[f] + beta * p[f];
    }
    for (size_t f = 0; f < nf; ++f)
      if (!x[f].allFinite()) return false;
    return true;
  }

  // Decrease of the quadratic model for the step just solved: (g.d + lambda d'Dd) / 2, as the
  // damped normal equations make d'Hd = g.d - lambda d'Dd.
  [[nodiscard]] double PredictedDecrease(double lambda) const {
    return 0.5 * (gradient_dot_delta_ + lambda * damping_term_);
  }

  const BundleAdjustmentProblem& in_;
  const BundleAdjustmentOptions& options_;
  const bool robust_, dense_, iterative_;
  const double bf_;
  SchurWorkspace& w_;
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>, Eigen::Upper> sparse_;
  bool parallel_ = false;
  std::optional<tbb::task_arena> arena_;
  bool sparse_analysed_ = false;
  double gradient_dot_delta_ = 0, damping_term_ = 0;
};

}  // namespace

SchurWorkspacePtr MakeSchurWorkspace() {
  return SchurWorkspacePtr(new SchurWorkspace);
}
void SchurWorkspaceDeleter::operator()(SchurWorkspace* w) const {
  delete w;
}

bool SolvePassSchurLm(const BundleAdjustmentProblem& input, const BundleAdjustmentOptions& options,
                      const std::vector<uint8_t>& active, bool robust, int iterations, bool dense,
                      std::vector<Eigen::Isometry3d>* poses, std::vector<Eigen::Vector3d>* points, int* iterations_done,
                      bool* stopped, SchurWorkspace* workspace) {
  SchurWorkspacePtr local;
  if (!workspace) {
    local = MakeSchurWorkspace();
    workspace = local.get();
  }
  std::vector<PoseState>& state = workspace->state;
  state.resize(poses->size());
  for (size_t k = 0; k < poses->size(); ++k) {
    state[k].R = (*poses)[k].linear();
    state[k].t = (*poses)[k].translation();
  }
  Solver solver(input, options, active, robust, dense, workspace);
  const bool ok = solver.Run(&state, points, iterations, iterations_done, stopped);
  for (size_t k = 0; k < poses->size(); ++k) {
    if (input.poses[k].fixed) continue;
    // Re-orthonormalize: many small rotation updates drift off SO(3) in the last bits.
    const Eigen::Quaterniond q(state[k].R);
    (*poses)[k].linear() = q.normalized().toRotationMatrix();
    (*poses)[k].translation() = state[k].t;
  }
  return ok;
}

}  // namespace flatslam::detail
