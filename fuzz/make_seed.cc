// Writes the fuzzer's seed corpus: small valid map snapshots (one map; several maps with agents,
// erased entities and loop edges; no maps at all) into SEED_DIR, and empties WORK_DIR, where the
// fuzzer keeps the inputs it finds.
#include <cstdio>
#include <filesystem>
#include <fstream>

#include "storage/random_map.h"
#include "storage/snapshot.h"

int main(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: %s SEED_DIR WORK_DIR\n", argv[0]);
    return 2;
  }
  const std::filesystem::path dir = argv[1], work = argv[2];
  std::filesystem::remove_all(work);
  std::filesystem::create_directories(work);
  std::filesystem::create_directories(dir);
  using flatslam::testing::RandomMap;
  using flatslam::testing::RandomMapOptions;
  RandomMapOptions small;
  small.keyframes = 3;
  small.keypoints = 6;
  small.points = 4;
  small.observations_per_point = 2;
  small.loop_edges = 0;
  small.erase_some = false;
  RandomMapOptions larger;
  larger.keyframes = 8;
  larger.keypoints = 12;
  larger.points = 20;
  larger.observations_per_point = 3;
  const flatslam::Map a = RandomMap(small), b = RandomMap(larger);
  flatslam::SnapshotMetadata metadata;
  metadata.calibration.camera = {500, 500, 320, 240, 640, 480};
  metadata.vocabulary_checksum = 77;
  const flatslam::SnapshotMapRef one[] = {{0, &a}};
  const flatslam::SnapshotMapRef two[] = {{1, &a}, {2, &b}};
  flatslam::SaveMapSnapshot(dir / "one_map.fsmap", one, metadata);
  flatslam::SaveMapSnapshot(dir / "two_maps.fsmap", two, metadata);
  flatslam::SaveMapSnapshot(dir / "no_maps.fsmap", {}, metadata);
  return 0;
}
