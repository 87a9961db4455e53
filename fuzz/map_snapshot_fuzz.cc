// libFuzzer target for map snapshots: any bytes given to the read-only view and to the bulk loader
// either verify or raise flatslam::Error; nothing may crash, hang or read out of bounds.
// Build and run: see fuzz/CMakeLists.txt (ctest -R map_snapshot_fuzz).
#include <cstddef>
#include <cstdint>
#include <span>

#include "core/error.h"
#include "storage/snapshot.h"

namespace {

// Touches everything the view serves, so the fuzzer checks the accessors as well as the verifier.
void ReadEverything(const flatslam::MapSnapshotView& view) {
  (void)view.calibration();
  (void)view.scales();
  (void)view.vocabulary_checksum();
  for (size_t m = 0; m < view.map_count(); ++m) {
    (void)view.map_id(m);
    for (uint32_t agent : view.agents(m)) (void)agent;
    (void)view.keypoint_count(m);
    (void)view.observation_count(m);
    (void)view.bounds(m);
    (void)view.KeyFrameTrajectory(m);
    for (size_t i = 0; i < view.point_count(m); ++i) (void)view.point_position(m, i);
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::span<const uint8_t> bytes(data, size);
  // Structure and index checks only: mutated inputs rarely keep a valid content hash, so this is
  // where the fuzzer reaches the verifier and loader in depth.
  flatslam::SnapshotReadOptions structural;
  structural.verify_content_hash = false;
  try {
    ReadEverything(flatslam::MapSnapshotView::FromBytes(bytes, "fuzz", structural));
  } catch (const flatslam::Error&) {
  }
  try {
    const flatslam::LoadedSnapshot loaded = flatslam::LoadMapSnapshotFromBytes(bytes, "fuzz", structural);
    for (const flatslam::LoadedMap& m : loaded.maps) (void)m.map.Validate();
  } catch (const flatslam::Error&) {
  }
  try {
    (void)flatslam::LoadMapSnapshotFromBytes(bytes, "fuzz");
  } catch (const flatslam::Error&) {
  }
  return 0;
}
