// Geometric verification of a place-recognition candidate, shared by loop closing (query and
// candidate in one map) and map merging (the query from another map): bag-of-words matches
// between the two keyframes, a Sim(3) (monocular) or SE(3) RANSAC on their map points, then every
// point around the candidate searched in the query keyframe at the estimated pose.
// Concurrency: reads both maps (the caller keeps writers out); rng is the caller's stream.
#pragma once

#include <cstddef>
#include <optional>
#include <random>
#include <vector>

#include "ecs/map.h"
#include "matching/matcher.h"
#include "geometry/similarity.h"

namespace flatslam {

struct PlaceVerificationOptions {
  int min_bow_matches = 20;        // bag-of-words pairs with map points on both sides, before RANSAC
  float bow_ratio = 0.75f;         // best/second-best ratio of those matches
  SimilarityRansacOptions ransac;  // fix_scale: true unless monocular
  size_t neighbours = 20;          // best covisible keyframes of the candidate whose points are searched
  float search_radius_px = 10;     // around each projected point, times its level scale

  [[nodiscard]] bool Check() const {
    return min_bow_matches >= 3 && bow_ratio > 0 && bow_ratio <= 1 && ransac.Check() && search_radius_px > 0;
  }
};

struct PlaceMatch {
  Similarity3 S_cw;                  // the query camera's pose in the candidate map's world
  std::vector<PointHandle> matched;  // per query keypoint: a candidate-map point, or null
  std::vector<PointHandle> nearby;   // the candidate-map points searched (candidate and neighbours)
  int matches = 0;                   // non-null entries of matched
};

// nullopt when too few bag-of-words matches or no RANSAC consensus; otherwise the match, whose
// count the caller holds to its own minimum.
[[nodiscard]] std::optional<PlaceMatch> VerifyPlace(const KeyFrame& query, const Map& query_map,
                                                    KeyFrameHandle candidate, const Map& candidate_map,
                                                    const CameraGeometry& geometry, const MatcherOptions& matcher,
                                                    const PlaceVerificationOptions& options, std::mt19937_64& rng);

}  // namespace flatslam
