#include "ecs/access.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

using C = Component;

TEST(Access, ConflictsWhenOneWritesWhatTheOtherTouches) {
  const Access read_map = Access::Of({C::kMap}, {});
  const Access write_map = Access::Of({}, {C::kMap});
  const Access write_index = Access::Of({C::kMap}, {C::kPlaceIndex});
  EXPECT_FALSE(read_map.ConflictsWith(read_map));
  EXPECT_TRUE(read_map.ConflictsWith(write_map));
  EXPECT_TRUE(write_map.ConflictsWith(read_map));
  EXPECT_FALSE(read_map.ConflictsWith(write_index));
  EXPECT_TRUE(write_map.ConflictsWith(write_index));
  EXPECT_EQ(write_map.ConflictWith(write_index), "map");
  EXPECT_EQ(Access::Of({C::kMap, C::kPlaceIndex}, {}).ConflictWith(Access::Of({}, {C::kMap, C::kPlaceIndex})),
            "map, place index");
}

TEST(AccessGuard, WritersOfAComponentNeverOverlap) {
  AccessGuard guard;
  std::atomic<int> inside{0};
  std::atomic<bool> overlapped{false};
  auto writer = [&](Access access) {
    for (int i = 0; i < 2000; ++i) {
      const auto lease = guard.Acquire(access);
      if (inside.fetch_add(1) != 0) overlapped = true;
      inside.fetch_sub(1);
    }
  };
  // Different component sets that share the map: always one at a time.
  std::thread a(writer, Access::Of({}, {C::kMap, C::kTracker}));
  std::thread b(writer, Access::Of({C::kPlaceIndex}, {C::kMap}));
  writer(Access::Of({}, {C::kLoops, C::kMap}));
  a.join();
  b.join();
  EXPECT_FALSE(overlapped);
}

TEST(AccessGuard, ReadersShareAComponent) {
  AccessGuard guard;
  std::atomic<int> inside{0};
  std::atomic<int> most{0};
  auto reader = [&] {
    const auto lease = guard.Acquire(Access::Of({C::kMap}, {}));
    const int now = inside.fetch_add(1) + 1;
    most = std::max(most.load(), now);
    // Wait (bounded) for the other reader to be inside too.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (inside.load() < 2 && std::chrono::steady_clock::now() < deadline) std::this_thread::yield();
    most = std::max(most.load(), inside.load());
  };
  std::thread a(reader);
  reader();
  a.join();
  EXPECT_EQ(most.load(), 2);
}

}  // namespace
}  // namespace flatslam
