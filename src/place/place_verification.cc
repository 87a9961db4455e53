#include "place/place_verification.h"

#include <algorithm>
#include <unordered_set>

#include "core/error.h"

namespace flatslam {

std::optional<PlaceMatch> VerifyPlace(const KeyFrame& query, const Map& query_map, KeyFrameHandle candidate,
                                      const Map& candidate_map, const CameraGeometry& geometry,
                                      const MatcherOptions& matcher, const PlaceVerificationOptions& options,
                                      std::mt19937_64& rng) {
  FLATSLAM_CHECK(options.Check(), "VerifyPlace: invalid PlaceVerificationOptions");
  const KeyFrame& c = candidate_map.keyframe(candidate);
  const auto pairs = MatchKeyFramesByBow(query, query_map, c, candidate_map, matcher, options.bow_ratio);
  if (static_cast<int>(pairs.size()) < options.min_bow_matches) return std::nullopt;
  const std::vector<PointCorrespondence> correspondences =
      CorrespondencesOf(query, query_map, c, candidate_map, pairs, geometry.pyramid);
  const auto result = EstimateSimilarityRansac(geometry.camera, correspondences, options.ransac, rng);
  if (!result) return std::nullopt;

  PlaceMatch out;
  out.S_cw = result->S_21.inverse() * Similarity3::FromIsometry(c.T_cam_world);
  out.matched.assign(query.size(), PointHandle::null());
  for (size_t k = 0; k < pairs.size(); ++k)
    if (result->inlier[k]) out.matched[pairs[k].first] = c.points[pairs[k].second];
  std::unordered_set<PointHandle> unique;
  std::vector<KeyFrameHandle> around = candidate_map.BestCovisible(candidate, options.neighbours);
  around.push_back(candidate);
  for (KeyFrameHandle h : around)
    for (PointHandle p : candidate_map.keyframe(h).points)
      if (candidate_map.points().contains(p) && unique.insert(p).second) out.nearby.push_back(p);
  MatchBySimilarity(query, out.S_cw, out.nearby, candidate_map, geometry, options.search_radius_px, matcher,
                    &out.matched);
  out.matches = static_cast<int>(
      std::count_if(out.matched.begin(), out.matched.end(), [](PointHandle p) { return !p.is_null(); }));
  return out;
}

}  // namespace flatslam
