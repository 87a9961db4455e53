#include "place/keyframe_database.h"

#include <algorithm>
#include <unordered_map>
#include <unordered_set>
#include <utility>
#include <vector>

#include "core/error.h"
#include "place/vocabulary.h"

namespace flatslam {

void KeyFrameDatabase::Add(KeyFrameHandle kf, const BowVector& bow) {
  for (const auto& [w, weight] : bow)
    FLATSLAM_CHECK(w < inverted_.size(), "word ", w, " outside the database's ", inverted_.size(), " words");
  if (!members_.insert(kf).second) return;
  for (const auto& [w, weight] : bow) inverted_[w].push_back(kf);
}

void KeyFrameDatabase::Erase(KeyFrameHandle kf, const BowVector& bow) {
  if (members_.erase(kf) == 0) return;  // never added (e.g. culled before local mapping reached it)
  for (const auto& [w, weight] : bow) {
    if (w >= inverted_.size()) continue;
    auto& list = inverted_[w];
    const auto it = std::find(list.begin(), list.end(), kf);
    if (it != list.end()) {
      *it = list.back();
      list.pop_back();
    }
  }
}

void KeyFrameDatabase::Clear() {
  for (auto& list : inverted_) list.clear();
  members_.clear();
}

std::vector<PlaceCandidate> KeyFrameDatabase::DetectLoopCandidates(const Map& map, KeyFrameHandle query,
                                                                   float min_score) const {
  return Rank(map, map.keyframe(query).bow, query, min_score);
}

std::vector<PlaceCandidate> KeyFrameDatabase::DetectRelocalizationCandidates(const Map& map,
                                                                             const BowVector& bow) const {
  return Rank(map, bow, KeyFrameHandle::null(), 0.0f);
}

std::vector<PlaceCandidate> KeyFrameDatabase::Rank(const Map& map, const BowVector& bow, KeyFrameHandle exclude_around,
                                                   float min_score) const {
  // Keyframes already connected to the query are not loop candidates.
  std::unordered_set<KeyFrameHandle> excluded;
  if (!exclude_around.is_null()) {
    excluded.insert(exclude_around);
    for (const auto& [n, w] : map.keyframe(exclude_around).covisible) excluded.insert(n);
  }
  // Words in common with the query, per keyframe, counted by arena slot: a query walks some ten
  // thousand entries of a few hundred keyframes. A slot counts the first handle met there; another
  // generation of it (a keyframe erased and its slot reused) is counted apart. Scratch per
  // thread, left at zero.
  thread_local std::vector<int> count_of_slot;
  thread_local std::vector<KeyFrameHandle> handle_of_slot;
  std::vector<KeyFrameHandle> seen;
  std::unordered_map<KeyFrameHandle, int> other_generation;
  for (const auto& [w, weight] : bow) {
    if (w >= inverted_.size()) continue;
    for (KeyFrameHandle kf : inverted_[w]) {
      if (!excluded.empty() && excluded.count(kf)) continue;
      const uint32_t slot = kf.index();
      if (slot >= count_of_slot.size()) {
        count_of_slot.resize(slot + 1, 0);
        handle_of_slot.resize(slot + 1);
      }
      if (count_of_slot[slot] == 0) {
        handle_of_slot[slot] = kf;
        seen.push_back(kf);
        count_of_slot[slot] = 1;
      } else if (handle_of_slot[slot] == kf) {
        ++count_of_slot[slot];
      } else {
        ++other_generation[kf];
      }
    }
  }
  std::vector<std::pair<KeyFrameHandle, int>> common;
  common.reserve(seen.size() + other_generation.size());
  for (KeyFrameHandle kf : seen) common.emplace_back(kf, std::exchange(count_of_slot[kf.index()], 0));
  common.insert(common.end(), other_generation.begin(), other_generation.end());
  if (common.empty()) return {};
  int max_common = 0;
  for (const auto& [kf, n] : common) max_common = std::max(max_common, n);
  const int min_common = static_cast<int>(0.8f * static_cast<float>(max_common));

  std::unordered_map<KeyFrameHandle, float> scored;
  for (const auto& [kf, n] : common) {
    if (n < min_common) continue;
    const KeyFrame* k = map.keyframes().try_get(kf);
    if (!k) continue;
    const float s = Vocabulary::Score(bow, k->bow);
    if (s >= min_score) scored.emplace(kf, s);
  }
  if (scored.empty()) return {};

  // Accumulate each candidate's score over its covisible candidates; keep the best of each group.
  std::vector<PlaceCandidate> groups;
  float best_group = 0;
  for (const auto& [kf, s] : scored) {
    PlaceCandidate c{kf, s, s};
    for (KeyFrameHandle n : map.BestCovisible(kf, 10)) {
      const auto it = scored.find(n);
      if (it == scored.end()) continue;
      c.group_score += it->second;
      if (it->second > c.score || (it->second == c.score && n < c.keyframe)) {
        c.score = it->second;
        c.keyframe = n;
      }
    }
    best_group = std::max(best_group, c.group_score);
    groups.push_back(c);
  }
  const float min_group = 0.75f * best_group;
  std::vector<PlaceCandidate> out;
  std::unordered_set<KeyFrameHandle> taken;
  std::sort(groups.begin(), groups.end(), [](const PlaceCandidate& a, const PlaceCandidate& b) {
    return a.group_score != b.group_score ? a.group_score > b.group_score : a.keyframe < b.keyframe;
  });
  for (const PlaceCandidate& c : groups)
    if (c.group_score >= min_group && taken.insert(c.keyframe).second) out.push_back(c);
  return out;
}

}  // namespace flatslam
