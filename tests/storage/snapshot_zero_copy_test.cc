// A read-only open of a large map snapshot allocates almost nothing: the view reads the mmap'ed
// file in place. Global operator new is replaced here to count heap allocations.
#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <new>

#include <gtest/gtest.h>

#include "storage/random_map.h"
#include "storage/snapshot.h"
#include "test_data.h"

namespace {
std::atomic<size_t> g_allocations{0};
std::atomic<size_t> g_bytes{0};
}  // namespace

void* operator new(size_t size) {
  ++g_allocations;
  g_bytes += size;
  if (void* p = std::malloc(size == 0 ? 1 : size)) return p;
  throw std::bad_alloc();
}
void* operator new[](size_t size) {
  return operator new(size);
}
// The replacements below free what the replacement new took from malloc. GCC 12 does not see
// that pairing where it inlines a delete next to its new and warns of a mismatch.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
void operator delete(void* p) noexcept {
  std::free(p);
}
void operator delete[](void* p) noexcept {
  std::free(p);
}
void operator delete(void* p, size_t) noexcept {
  std::free(p);
}
void operator delete[](void* p, size_t) noexcept {
  std::free(p);
}
#pragma GCC diagnostic pop

namespace flatslam {
namespace {

struct Counted {
  size_t allocations = 0, bytes = 0;
};

template <class Fn>
Counted Count(Fn&& fn) {
  const size_t a0 = g_allocations, b0 = g_bytes;
  fn();
  return {g_allocations - a0, g_bytes - b0};
}

TEST(MapSnapshotZeroCopy, ReadOnlyOpenAllocatesAlmostNothing) {
  const auto dir = testing::FreshTempDir("snapshot_zero_copy");
  const std::filesystem::path path = dir / "large.fsmap";
  {
    testing::RandomMapOptions o;
    o.keyframes = 200;
    o.keypoints = 2000;
    o.points = 40000;
    o.observations_per_point = 5;
    const Map map = testing::RandomMap(o);
    const SnapshotMapRef ref{0, &map};
    SaveMapSnapshot(path, {&ref, 1}, SnapshotMetadata{});
  }
  const size_t file_size = std::filesystem::file_size(path);
  ASSERT_GT(file_size, 20u << 20);

  for (const bool hash : {false, true}) {
    SnapshotReadOptions options;
    options.verify_content_hash = hash;
    size_t keyframes = 0, points = 0;
    double extent = 0;
    const Counted c = Count([&] {
      const MapSnapshotView view = MapSnapshotView::Open(path, options);
      keyframes = view.keyframe_count(0);
      points = view.point_count(0);
      const BoundingBox box = view.bounds(0);
      extent = (box.max - box.min).norm();
    });
    std::printf("open (content hash %s) of a %.1f MiB snapshot: %zu allocations, %zu bytes\n", hash ? "on" : "off",
                file_size / 1048576.0, c.allocations, c.bytes);
    EXPECT_EQ(keyframes, 199u);  // one keyframe erased by RandomMap
    EXPECT_GT(points, 39000u);
    EXPECT_GT(extent, 10.0);
    // The path string, the file name and one keypoint count per keyframe (199 x 4 bytes).
    EXPECT_LE(c.allocations, 8u);
    EXPECT_LE(c.bytes, 4096u);
  }

  // For scale: the full load allocates about as much as the file holds.
  const Counted load = Count([&] { (void)LoadMapSnapshot(path); });
  std::printf("full load: %zu allocations, %zu bytes\n", load.allocations, load.bytes);
  EXPECT_GT(load.bytes, file_size / 2);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace flatslam
