// Keyframe database for place recognition: an inverted index from vocabulary word to the
// keyframes containing it, queried for loop and relocalization candidates with DBoW2 L1 scores,
// candidates grouped by covisibility as ORB-SLAM2 does.
// Concurrency: not synchronized. Add/Erase and queries run under the caller's map lock.
#pragma once

#include <cstddef>
#include <cstdint>
#include <unordered_set>
#include <vector>

#include "ecs/bow.h"
#include "ecs/map.h"

namespace flatslam {

struct PlaceCandidate {
  KeyFrameHandle keyframe;
  float score = 0;        // L1 score against the query
  float group_score = 0;  // accumulated over its covisible candidates
};

class KeyFrameDatabase {
 public:
  explicit KeyFrameDatabase(size_t word_count = 0) : inverted_(word_count) {}

  // Indexes kf under the words of bow (bow must stay as it was for Erase); once per keyframe.
  void Add(KeyFrameHandle kf, const BowVector& bow);
  void Erase(KeyFrameHandle kf, const BowVector& bow);
  void Clear();
  [[nodiscard]] size_t size() const { return members_.size(); }
  [[nodiscard]] bool contains(KeyFrameHandle kf) const { return members_.count(kf) > 0; }
  [[nodiscard]] size_t word_count() const { return inverted_.size(); }
  [[nodiscard]] const std::vector<KeyFrameHandle>& keyframes_with(WordId w) const { return inverted_[w]; }

  // Loop candidates for keyframe `query` of `map`: keyframes not covisible with it that share
  // at least 80% of the best count of common words, score at least `min_score`, and whose
  // covisibility group (candidate plus its 10 best covisible candidates) accumulates at least
  // 75% of the best group score. One keyframe (the best scored) per group.
  [[nodiscard]] std::vector<PlaceCandidate> DetectLoopCandidates(const Map& map, KeyFrameHandle query,
                                                                 float min_score) const;
  // Relocalization candidates for a frame with bag of words `bow`: same ranking, no exclusion,
  // no minimum score.
  [[nodiscard]] std::vector<PlaceCandidate> DetectRelocalizationCandidates(const Map& map, const BowVector& bow) const;

 private:
  [[nodiscard]] std::vector<PlaceCandidate> Rank(const Map& map, const BowVector& bow, KeyFrameHandle exclude_around,
                                                 float min_score) const;

  std::vector<std::vector<KeyFrameHandle>> inverted_;
  std::unordered_set<KeyFrameHandle> members_;
};

}  // namespace flatslam
