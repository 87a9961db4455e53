#include "core/object_pool.h"

#include <atomic>
#include <vector>

#include <gtest/gtest.h>
#include <tbb/parallel_for.h>

namespace flatslam {
namespace {

TEST(ObjectPool, ReleasedObjectsAreReusedWithTheirCapacity) {
  ObjectPool<std::vector<int>> pool;
  const std::vector<int>* first = nullptr;
  {
    auto lease = pool.Acquire();
    lease->resize(1000);
    first = lease.get();
    EXPECT_EQ(pool.idle(), 0u);
  }
  EXPECT_EQ(pool.idle(), 1u);
  auto again = pool.Acquire();
  EXPECT_EQ(again.get(), first);        // the same object comes back
  EXPECT_GE(again->capacity(), 1000u);  // with its buffer
  EXPECT_EQ(pool.idle(), 0u);
}

TEST(ObjectPool, LeasesHeldAtOnceAreDistinct) {
  ObjectPool<int> pool;
  auto a = pool.Acquire();
  auto b = pool.Acquire();
  EXPECT_NE(a.get(), b.get());
  auto moved = std::move(a);  // a moved lease returns its object once, not twice
  (void)moved;
}

// Many threads acquiring and releasing: never two holders of one object, and the pool ends up
// holding at most as many objects as were in use at once.
TEST(ObjectPool, ConcurrentUseNeverSharesAnObject) {
  ObjectPool<int> pool;
  std::atomic<int> in_use{0}, most_in_use{0}, conflicts{0};
  tbb::parallel_for(0, 20000, [&](int i) {
    // Counted from before the lease exists until after it is released, so in_use never
    // undercounts the leases alive at once (the bound checked below).
    const int now = ++in_use;
    int seen = most_in_use.load();
    while (now > seen && !most_in_use.compare_exchange_weak(seen, now)) {
    }
    {
      auto lease = pool.Acquire();
      if (*lease != 0) ++conflicts;  // another holder's mark is still there
      *lease = i + 1;
      volatile int spin = 0;  // a short hold the compiler cannot drop
      while (spin < 100) spin = spin + 1;
      if (*lease != i + 1) ++conflicts;  // another holder wrote meanwhile
      *lease = 0;
    }
    --in_use;
  });
  EXPECT_EQ(conflicts.load(), 0);
  EXPECT_GE(pool.idle(), 1u);
  EXPECT_LE(pool.idle(), static_cast<size_t>(most_in_use.load()));
}

}  // namespace
}  // namespace flatslam
