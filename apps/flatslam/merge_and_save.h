// Merging several maps and writing the result, as `flatslam map merge` and `flatslam server` do:
// place recognition between the maps, the merges of the overlap graph's spanning tree, one line
// per overlap, attempt and output map on stdout, and one snapshot holding every output map.
// Concurrency: blocks the caller; uses the merge's threads.
#pragma once

#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "ecs/map.h"
#include "merge/map_merge.h"
#include "place/vocabulary.h"
#include "storage/snapshot.h"

namespace flatslam::app {

// The RGB-D virtual baseline the maps were built with (SlamOptions' default when not recorded).
[[nodiscard]] double VirtualBaseline(const SnapshotMetadata& metadata);
// The agents of a map's keyframes, "0,2".
[[nodiscard]] std::string Agents(const Map& map);

struct MergeTimes {
  double merge_ms = 0, save_ms = 0;
  size_t output_maps = 0;
};
// Throws flatslam::Error when a merged map is inconsistent or the snapshot cannot be written.
// on_merged, when given, sees the merge before the snapshot is written.
MergeTimes MergeAndSave(std::vector<Map> maps, const Vocabulary& vocabulary, const SnapshotMetadata& metadata,
                        const MapMergeOptions& options, const std::filesystem::path& out_path,
                        const std::function<void(const MultiMapMerge&)>& on_merged = {});

}  // namespace flatslam::app
