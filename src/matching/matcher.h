// Descriptor matching guided by geometry: projection search (frame to frame, local map to
// frame), epipolar search for triangulation, and fusion of duplicate map points.
// Concurrency: pure functions of their inputs; the caller holds the map lock they need.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Core>

#include "ecs/map.h"
#include "core/option_fields.h"
#include "io/types.h"
#include "frontend/features.h"
#include "frontend/frame.h"
#include "geometry/camera.h"
#include "geometry/similarity.h"

namespace flatslam {

// The searches' options: X(type, name, default, requirement, description) (core/option_fields.h).
#define FLATSLAM_MATCHER_OPTIONS(X)                                                                                 \
  X(int, max_distance, 100, max_distance > 0, "Hamming gate for projection search (ORB-SLAM2's TH_HIGH)")           \
  X(int, max_distance_strict, 50, max_distance_strict > 0, "Hamming gate for triangulation and fusion (TH_LOW)")    \
  X(float, nn_ratio, 0.8f, nn_ratio > 0 && nn_ratio <= 1, "best / second best at the same level, local-map search") \
  X(bool, check_orientation, true, true, "keep matches whose rotation agrees with the dominant ones")               \
  X(float, fusion_radius, 3.0f, fusion_radius > 0, "pixels at level 0, times the level scale")

struct MatcherOptions {
  FLATSLAM_MATCHER_OPTIONS(FLATSLAM_OPTION_FIELD)

  FLATSLAM_OPTION_MEMBERS(FLATSLAM_MATCHER_OPTIONS)
  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const { return FieldsProblem(); }
  [[nodiscard]] bool Check() const { return Problem().empty(); }
};

// Matches the map points seen by `source` (a previous frame) into `current`, whose pose is set.
// Only unmatched keypoints of current are taken. Returns the number of new matches.
int MatchByProjection(TrackedFrame& current, const TrackedFrame& source, const Map& map, const CameraGeometry& geometry,
                      float radius, const MatcherOptions& options);
// Same, from the map points of a keyframe.
int MatchByProjection(TrackedFrame& current, const KeyFrame& source, const Map& map, const CameraGeometry& geometry,
                      float radius, const MatcherOptions& options);
// Matches local map points (not yet matched in current) that fall in the frustum of current,
// at the level predicted from their distance. Updates `visible` counts through `seen` (the
// points that passed the frustum test are appended). Returns the number of new matches.
int MatchLocalPoints(TrackedFrame& current, const Map& map, std::span<const PointHandle> points,
                     const CameraGeometry& geometry, float radius_scale, const MatcherOptions& options,
                     std::vector<PointHandle>* seen);

// Pairs of keypoints of kf1 and kf2 that have no map point, agree in descriptor, satisfy the
// epipolar constraint of F_2_1 (x2^T F x1 = 0) and, stereo aside, lie away from the epipole.
// Candidates come from near the projection of a measured depth, else from the epipolar
// segment of depth_range (metres along the optical axis of kf1).
std::vector<std::pair<uint32_t, uint32_t>> MatchForTriangulation(const KeyFrame& kf1, const KeyFrame& kf2,
                                                                 const Eigen::Matrix3d& F_2_1,
                                                                 std::pair<double, double> depth_range,
                                                                 const CameraGeometry& geometry,
                                                                 const MatcherOptions& options);

// Projects `points` into kf and either adds an observation (free keypoint) or merges with the
// point already there (the one with more observations survives). Returns the number of fusions.
// Equals ApplyFusion(map, kf, FindFusion(map, kf, points, ...)).
int FusePoints(Map& map, KeyFrameHandle kf, std::span<const PointHandle> points, const CameraGeometry& geometry,
               const MatcherOptions& options);

// FusePoints in two steps. FindFusion reads the map (callers may run it for several keyframes at
// once): for each point of `points` that kf does not observe, the keypoint of kf it matches, if
// any. ApplyFusion writes the map: each match in order, skipping a point erased or already seen
// by kf since. The keypoint a point matches depends only on the point's position, normal,
// distance range and descriptor and on kf's keypoints, none of which a fusion changes, so
// finding the matches of several keyframes first and applying them keyframe by keyframe gives
// the map FusePoints does, keyframe by keyframe.
std::vector<std::pair<PointHandle, uint32_t>> FindFusion(const Map& map, KeyFrameHandle kf,
                                                         std::span<const PointHandle> points,
                                                         const CameraGeometry& geometry, const MatcherOptions& options);
int ApplyFusion(Map& map, KeyFrameHandle kf, std::span<const std::pair<PointHandle, uint32_t>> matches);

// Monocular initialization: for each keypoint of `first`, the best keypoint of `second` within
// `window` pixels of the same position at the same level (ratio and orientation checked).
// Returns pairs (index in first, index in second).
std::vector<std::pair<uint32_t, uint32_t>> MatchForInitialization(const TrackedFrame& first, const TrackedFrame& second,
                                                                  float window, const MatcherOptions& options);

// Bag-of-words search: keypoints compared only within the same vocabulary node (direct index),
// best Hamming distance under max_distance_strict with a best/second-best ratio, orientation
// checked. Map points of kf go to free keypoints of frame; returns the number of matches.
int MatchByBow(TrackedFrame& frame, const KeyFrame& kf, const Map& map, const MatcherOptions& options,
               float ratio = 0.75f);
// Keypoint pairs (i1 in a, i2 in b) where both keypoints carry live map points (a's in map_a,
// b's in map_b: one map for loop closing, two for map merging).
std::vector<std::pair<uint32_t, uint32_t>> MatchKeyFramesByBow(const KeyFrame& a, const Map& map_a, const KeyFrame& b,
                                                               const Map& map_b, const MatcherOptions& options,
                                                               float ratio = 0.75f);

// Projects world points through S_cw (X_c = s R X + t; a corrected pose across a loop) into kf
// and binds each to the best keypoint within radius x level scale at the level predicted from
// its distance, under max_distance_strict. (*matched)[k] is the point for keypoint k (sized to
// kf); entries already set are kept. Returns the number of new matches.
int MatchBySimilarity(const KeyFrame& kf, const Similarity3& S_cw, std::span<const PointHandle> points, const Map& map,
                      const CameraGeometry& geometry, float radius, const MatcherOptions& options,
                      std::vector<PointHandle>* matched);

// 3D-3D correspondences of matched keypoint pairs (i in a, j in b, both with live points): each
// point in its own keyframe's camera frame, with the observing pixels and level variances.
std::vector<PointCorrespondence> CorrespondencesOf(const KeyFrame& a, const Map& map_a, const KeyFrame& b,
                                                   const Map& map_b,
                                                   std::span<const std::pair<uint32_t, uint32_t>> pairs,
                                                   const ScalePyramid& pyramid);

// Fundamental matrix mapping pixels of kf1 to epipolar lines in kf2.
[[nodiscard]] Eigen::Matrix3d FundamentalBetween(const KeyFrame& kf1, const KeyFrame& kf2, const PinholeCamera& camera);

}  // namespace flatslam
