// Bag-of-words vectors of a keyframe or frame, as flat sorted arrays.
// Concurrency: plain values.
#pragma once

#include <cstdint>
#include <utility>
#include <vector>

namespace flatslam {

using WordId = uint32_t;  // index of a vocabulary word (leaf), in [0, Vocabulary::word_count())

// TF-IDF weights per word, sorted by word, L1-normalized (weights sum to 1).
using BowVector = std::vector<std::pair<WordId, float>>;

// Direct index: (vocabulary node at the direct-index depth, keypoint index), sorted by node then
// keypoint. Matching two images compares only keypoints that fall under the same node.
using FeatureVector = std::vector<std::pair<uint32_t, uint32_t>>;

}  // namespace flatslam
