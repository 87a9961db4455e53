// Internal to bundle_adjustment.cc: the hand-written Levenberg-Marquardt solver on the reduced
// camera system (see BundleAdjustmentOptions::Solver::kSchurLm).
// Concurrency: stateless; one call owns its buffers. Its passes over the points (linearization,
// cost, elimination, back-substitution) run on options.schur_lm_threads TBB workers, split into
// fixed slices whose sums are made in slice order: the same bits on any number of threads.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include "optimization/bundle_adjustment.h"

namespace flatslam::detail {

// Iterative Schur: conjugate gradients stop when the residual of the reduced camera system is this
// fraction of its right-hand side (the forcing term of an inexact Newton step). A merged map's
// long-range bend, which adjusting a whole map is for, converges last: a loose term (Ceres'
// default, 0.1) leaves most of it to iterations a bounded adjustment does not run.
inline constexpr double kIterativeSchurTolerance = 1e-2;
inline constexpr int kIterativeSchurMaxSteps = 500;

// The iterative Schur product's kernel over points [j0, j1): for each point, t = sum of W' p over
// its observations with a free pose (obs_free >= 0), u = V_inv t, then partial -= W u at each of
// them. obs_start: CSR of observations by point; W: 18 doubles per observation (6x3,
// column-major); p and partial: 6 doubles per free pose. The AVX2 variant (x86-64 only; callers
// check HasAvx2Fma()) computes the same sums with fused multiply-adds, in another order.
void SchurProductSlice(const uint32_t* obs_start, const int* obs_free, const double* W, const Eigen::Matrix3d* V_inv,
                       const double* p, double* partial, size_t j0, size_t j1);
#if defined(__x86_64__)
void SchurProductSliceAvx2(const uint32_t* obs_start, const int* obs_free, const double* W,
                           const Eigen::Matrix3d* V_inv, const double* p, double* partial, size_t j0, size_t j1);
#endif

// One block of the reduced camera system less a product of two observations' blocks:
// S (6x6) -= A B' for A, B 6x3 (all column-major). Each element is S - ((A0 B0 + A1 B1) + A2 B2)
// with separate multiplies and adds, the order Eigen's product of fixed-size blocks takes, so
// both variants give the same bits; the AVX variant (x86-64 only; callers check HasAvx2()) does
// four rows at once.
void SubtractBlockProduct(double* S, const double* A, const double* B);
#if defined(__x86_64__)
void SubtractBlockProductAvx(double* S, const double* A, const double* B);
#endif

using SchurWorkspacePtr = std::unique_ptr<SchurWorkspace, SchurWorkspaceDeleter>;
[[nodiscard]] SchurWorkspacePtr MakeSchurWorkspace();

// One pass over the active observations: up to `iterations` LM iterations (each counted in
// *iterations_done), Huber-robust when `robust`. Fixed poses are read, never written. The pose
// system is solved densely when `dense`, else by sparse LDLT. *stopped is set when
// options.stop_early ended the pass. False on numerical failure (the state is the last accepted).
// `workspace` (may be null) keeps buffers between calls.
bool SolvePassSchurLm(const BundleAdjustmentProblem& input, const BundleAdjustmentOptions& options,
                      const std::vector<uint8_t>& active, bool robust, int iterations, bool dense,
                      std::vector<Eigen::Isometry3d>* poses, std::vector<Eigen::Vector3d>* points, int* iterations_done,
                      bool* stopped, SchurWorkspace* workspace);

}  // namespace flatslam::detail
