#include "ecs/arena.h"

#include <algorithm>
#include <cstdint>
#include <memory>
#include <random>
#include <sstream>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <utility>
#include <vector>

#include <gtest/gtest.h>

#include "core/error.h"
#include "ecs/handle.h"

namespace flatslam {
namespace {

struct Point {
  uint64_t id = 0;
  double x = 0.0;
};

// Counts constructions and destructions and remembers live addresses, so a double
// destruction or a destruction of something never built is caught without UB.
struct Tracked {
  static inline int constructed = 0;
  static inline int destroyed = 0;
  static inline int bad_destroys = 0;
  static inline std::unordered_set<const Tracked*> live;

  static void Reset() {
    constructed = destroyed = bad_destroys = 0;
    live.clear();
  }

  explicit Tracked(int v) : value(v) { Born(); }
  Tracked(const Tracked& other) : value(other.value) { Born(); }
  Tracked(Tracked&& other) noexcept : value(other.value) { Born(); }
  Tracked& operator=(const Tracked&) = default;
  Tracked& operator=(Tracked&&) noexcept = default;
  ~Tracked() {
    if (live.erase(this) != 1) ++bad_destroys;
    ++destroyed;
  }

  void Born() {
    live.insert(this);
    ++constructed;
  }

  int value;
};

// A constructor that throws on request, for exception-safety checks.
struct MaybeThrows {
  explicit MaybeThrows(bool fail) {
    if (fail) throw std::runtime_error("constructor failed");
  }
};

std::string ToString(const auto& h) {
  std::ostringstream out;
  out << h;
  return out.str();
}

// Expects get(h) to throw flatslam::Error whose message names the handle.
template <class ArenaT, class H>
void ExpectGetThrowsNaming(ArenaT& arena, H h) {
  try {
    (void)arena.get(h);
    ADD_FAILURE() << "expected flatslam::Error for " << h;
  } catch (const Error& e) {
    const std::string what = e.what();
    EXPECT_NE(what.find(ToString(h)), std::string::npos) << what;
    EXPECT_NE(what.find("stale"), std::string::npos) << what;
  }
  const ArenaT& const_arena = arena;
  EXPECT_THROW((void)const_arena.get(h), Error);
}

// ---------------------------------------------------------------------------------------
// Arena

TEST(Arena, CreateAndGet) {
  Arena<Point> arena;
  EXPECT_TRUE(arena.empty());
  const auto a = arena.create(Point{1, 1.5});
  const auto b = arena.create(Point{2, 2.5});
  EXPECT_NE(a, b);
  EXPECT_FALSE(a.is_null());
  EXPECT_EQ(arena.size(), 2u);
  EXPECT_TRUE(arena.contains(a));
  EXPECT_TRUE(arena.contains(b));
  EXPECT_EQ(arena.get(a).id, 1u);
  EXPECT_EQ(arena.get(b).x, 2.5);
  arena.get(a).x = 9.0;
  EXPECT_EQ(arena.try_get(a)->x, 9.0);
  const Arena<Point>& const_arena = arena;
  EXPECT_EQ(const_arena.get(a).x, 9.0);
  EXPECT_EQ(const_arena.try_get(b)->id, 2u);
}

TEST(Arena, EraseBumpsGeneration) {
  Arena<Point> arena;
  const auto h = arena.create(Point{7, 0.0});
  EXPECT_TRUE(arena.erase(h));
  EXPECT_FALSE(arena.contains(h));
  EXPECT_EQ(arena.try_get(h), nullptr);
  EXPECT_EQ(std::as_const(arena).try_get(h), nullptr);
  ExpectGetThrowsNaming(arena, h);
  EXPECT_FALSE(arena.erase(h)) << "second erase of a stale handle must be a no-op";
  EXPECT_TRUE(arena.empty());
  EXPECT_THROW((void)arena.dense_index(h), Error);

  const auto reused = arena.create(Point{8, 0.0});
  EXPECT_EQ(reused.index(), h.index());
  EXPECT_EQ(reused.generation(), h.generation() + 1);
  EXPECT_FALSE(arena.contains(h)) << "stale handle must not see the slot's new occupant";
  EXPECT_EQ(arena.try_get(h), nullptr);
  EXPECT_EQ(arena.get(reused).id, 8u);
}

TEST(Arena, ErrorMessageNamesTheHandle) {
  Arena<Point> arena;
  const auto h = arena.create();
  arena.erase(h);
  try {
    (void)arena.get(h);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("Handle(0v0)"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("Arena"), std::string::npos) << e.what();
  }
}

TEST(Arena, NullAndOutOfRangeHandlesAreNeverContained) {
  Arena<Point> arena;
  const auto live = arena.create();
  const Handle<Point> null;
  EXPECT_FALSE(arena.contains(null));
  EXPECT_EQ(arena.try_get(null), nullptr);
  EXPECT_FALSE(arena.erase(null));
  ExpectGetThrowsNaming(arena, null);

  const Handle<Point> out_of_range(1000, 0);
  EXPECT_FALSE(arena.contains(out_of_range));
  EXPECT_FALSE(arena.erase(out_of_range));
  ExpectGetThrowsNaming(arena, out_of_range);

  const Handle<Point> future(live.index(), live.generation() + 1);
  EXPECT_FALSE(arena.contains(future));
  EXPECT_FALSE(arena.erase(future));
  EXPECT_EQ(arena.size(), 1u);
}

TEST(Arena, ReusesErasedSlot) {
  Arena<Point> arena;
  const auto a = arena.create(Point{1});
  const auto b = arena.create(Point{2});
  const auto c = arena.create(Point{3});
  ASSERT_TRUE(arena.erase(b));
  const auto d = arena.create(Point{4});
  EXPECT_EQ(d.index(), b.index());
  EXPECT_NE(d, b);
  EXPECT_EQ(arena.slot_count(), 3u);
  EXPECT_EQ(arena.get(a).id, 1u);
  EXPECT_EQ(arena.get(c).id, 3u);
  EXPECT_EQ(arena.get(d).id, 4u);
  EXPECT_FALSE(arena.contains(b));
}

TEST(Arena, ChurnKeepsMemoryBounded) {
  constexpr int kLive = 100;
  constexpr int kCycles = 100'000;
  Arena<Point> arena;
  std::vector<Handle<Point>> live;
  for (int i = 0; i < kLive; ++i) live.push_back(arena.create(Point{uint64_t(i)}));
  const size_t capacity = arena.capacity();
  std::mt19937 rng(7);
  std::unordered_set<Handle<Point>> seen(live.begin(), live.end());
  for (int cycle = 0; cycle < kCycles; ++cycle) {
    const size_t k = rng() % live.size();
    ASSERT_TRUE(arena.erase(live[k]));
    const auto h = arena.create(Point{uint64_t(kLive + cycle)});
    // Every handle ever handed out is unique, even though slots are recycled.
    ASSERT_TRUE(seen.insert(h).second) << h;
    live[k] = h;
  }
  EXPECT_EQ(arena.size(), size_t{kLive});
  EXPECT_EQ(arena.slot_count(), size_t{kLive});
  EXPECT_EQ(arena.capacity(), capacity);
}

TEST(Arena, EraseIfRemovesMatching) {
  Arena<Point> arena;
  std::vector<Handle<Point>> handles;
  for (uint64_t i = 0; i < 1000; ++i) handles.push_back(arena.create(Point{i}));
  const size_t erased = arena.erase_if([](Handle<Point>, const Point& p) { return p.id % 3 != 1; });
  EXPECT_EQ(erased, 667u);
  EXPECT_EQ(arena.size(), 333u);
  for (uint64_t i = 0; i < 1000; ++i) {
    EXPECT_EQ(arena.contains(handles[i]), i % 3 == 1) << i;
    if (i % 3 == 1) {
      EXPECT_EQ(arena.get(handles[i]).id, i);
    }
  }
  for (size_t i = 0; i < arena.size(); ++i) {
    EXPECT_EQ(arena.values()[i].id % 3, 1u);
    EXPECT_EQ(arena.dense_index(arena.handles()[i]), i);
  }
  // The predicate sees each entity exactly once, with its own handle.
  size_t calls = 0;
  arena.erase_if([&](Handle<Point> h, const Point& p) {
    ++calls;
    EXPECT_EQ(arena.get(h).id, p.id);
    return false;
  });
  EXPECT_EQ(calls, 333u);
  EXPECT_EQ(arena.erase_if([](Handle<Point>, const Point&) { return true; }), 333u);
  EXPECT_TRUE(arena.empty());
}

TEST(Arena, BackwardIterationMayEraseCurrent) {
  Arena<Point> arena;
  std::vector<Handle<Point>> handles;
  for (uint64_t i = 0; i < 1000; ++i) handles.push_back(arena.create(Point{i}));
  std::vector<uint64_t> visited;
  for (size_t i = arena.size(); i-- > 0;) {
    const Handle<Point> h = arena.handles()[i];
    visited.push_back(arena.values()[i].id);
    EXPECT_EQ(arena.get(h).id, arena.values()[i].id);
    if (arena.values()[i].id % 2 == 0) {
      ASSERT_TRUE(arena.erase(h));
    }
  }
  std::sort(visited.begin(), visited.end());
  ASSERT_EQ(visited.size(), 1000u) << "each entity visited exactly once";
  for (uint64_t i = 0; i < 1000; ++i) EXPECT_EQ(visited[i], i);
  EXPECT_EQ(arena.size(), 500u);
  for (uint64_t i = 0; i < 1000; ++i) EXPECT_EQ(arena.contains(handles[i]), i % 2 == 1);
}

// Fast path (packed spans) against a reference model (hash map keyed by handle).
TEST(Arena, MatchesReferenceModelUnderRandomOps) {
  constexpr int kOps = 100'000;
  Arena<Point> arena;
  std::unordered_map<Handle<Point>, uint64_t> model;
  std::vector<Handle<Point>> live;   // keys of model, for uniform picks
  std::vector<Handle<Point>> stale;  // a sample of erased handles
  std::mt19937_64 rng(20240611);
  uint64_t next_id = 0;
  size_t max_live = 0;

  auto check_all = [&] {
    ASSERT_EQ(arena.size(), model.size());
    ASSERT_EQ(arena.values().size(), arena.handles().size());
    std::unordered_set<Handle<Point>> handles_seen;
    for (size_t i = 0; i < arena.size(); ++i) {
      const Handle<Point> h = arena.handles()[i];
      ASSERT_TRUE(handles_seen.insert(h).second) << "duplicate handle " << h;
      const auto it = model.find(h);
      ASSERT_NE(it, model.end()) << h;
      ASSERT_EQ(arena.values()[i].id, it->second) << h;
      ASSERT_EQ(arena.dense_index(h), i);
      ASSERT_EQ(&arena.get(h), &arena.values()[i]);
    }
    for (const auto& [h, id] : model) ASSERT_EQ(arena.get(h).id, id);
    for (const auto& h : stale) {
      ASSERT_FALSE(arena.contains(h)) << h;
      ASSERT_EQ(arena.try_get(h), nullptr) << h;
    }
  };

  auto erase_live = [&](size_t k) {
    const Handle<Point> h = live[k];
    ASSERT_TRUE(arena.erase(h));
    model.erase(h);
    live[k] = live.back();
    live.pop_back();
    if (stale.size() < 4096) {
      stale.push_back(h);
    } else {
      stale[rng() % stale.size()] = h;
    }
  };

  for (int op = 0; op < kOps; ++op) {
    const uint64_t r = rng() % 100;
    // Grow for a while, then shrink, so the arena both fills and drains.
    const bool growing = (op / 20'000) % 2 == 0;
    if (r < (growing ? 55u : 35u) || live.empty()) {
      const auto h = arena.create(Point{next_id, 0.0});
      ASSERT_TRUE(model.emplace(h, next_id).second) << "handle reused while live: " << h;
      live.push_back(h);
      ++next_id;
    } else if (r < 90) {
      erase_live(rng() % live.size());
    } else if (r < 95) {
      // Write through get() and check it is seen through values().
      const Handle<Point> h = live[rng() % live.size()];
      arena.get(h).id = next_id;
      model[h] = next_id++;
      ASSERT_EQ(arena.values()[arena.dense_index(h)].id, model[h]);
    } else if (r < 99) {
      if (!stale.empty()) {
        const Handle<Point> h = stale[rng() % stale.size()];
        ASSERT_FALSE(arena.erase(h));
        ASSERT_EQ(arena.try_get(h), nullptr);
      }
    } else {
      // A small erase_if sweep over ids with a given residue.
      const uint64_t residue = rng() % 64;
      const size_t before = arena.size();
      const size_t erased = arena.erase_if([&](Handle<Point>, const Point& p) { return p.id % 64 == residue; });
      for (size_t k = live.size(); k-- > 0;) {
        if (model[live[k]] % 64 != residue) continue;
        const Handle<Point> h = live[k];
        model.erase(h);
        live[k] = live.back();
        live.pop_back();
        if (stale.size() < 4096) stale.push_back(h);
      }
      ASSERT_EQ(before - erased, model.size());
    }
    max_live = std::max(max_live, live.size());
    if (op % 1000 == 0) check_all();
    if (HasFatalFailure()) return;
  }
  check_all();
  // Slots are recycled: never more slots than the most entities alive at once.
  EXPECT_EQ(arena.slot_count(), max_live);
}

TEST(Arena, ClearInvalidatesOldHandles) {
  Arena<Point> arena;
  std::vector<Handle<Point>> old;
  for (uint64_t i = 0; i < 50; ++i) old.push_back(arena.create(Point{i}));
  for (int i = 0; i < 10; ++i) arena.erase(old[i * 5]);
  arena.clear();
  EXPECT_TRUE(arena.empty());
  EXPECT_TRUE(arena.values().empty());
  EXPECT_TRUE(arena.handles().empty());
  for (const auto& h : old) {
    EXPECT_FALSE(arena.contains(h)) << h;
    EXPECT_EQ(arena.try_get(h), nullptr);
    EXPECT_FALSE(arena.erase(h));
  }
  // Slots are reused after clear, with handles none of the old ones equal.
  std::unordered_set<Handle<Point>> old_set(old.begin(), old.end());
  for (uint64_t i = 0; i < 50; ++i) {
    const auto h = arena.create(Point{100 + i});
    EXPECT_EQ(old_set.count(h), 0u) << h;
  }
  EXPECT_EQ(arena.slot_count(), 50u);
  for (const auto& h : old) EXPECT_FALSE(arena.contains(h)) << h;
  // Clearing again keeps everything stale.
  arena.clear();
  for (const auto& h : old) EXPECT_FALSE(arena.contains(h)) << h;
}

TEST(Arena, DestructorsRunExactlyOnce) {
  Tracked::Reset();
  {
    Arena<Tracked> arena;
    std::vector<Handle<Tracked>> handles;
    for (int i = 0; i < 500; ++i) handles.push_back(arena.create(i));
    EXPECT_EQ(Tracked::live.size(), arena.size());
    for (int i = 0; i < 500; i += 3) arena.erase(handles[i]);
    EXPECT_EQ(Tracked::live.size(), arena.size());
    arena.erase_if([](Handle<Tracked>, const Tracked& t) { return t.value % 5 == 0; });
    EXPECT_EQ(Tracked::live.size(), arena.size());
    for (int i = 0; i < 500; ++i) {
      if (const Tracked* t = arena.try_get(handles[i])) {
        EXPECT_EQ(t->value, i);
      }
    }
    arena.clear();
    EXPECT_TRUE(Tracked::live.empty());
    for (int i = 0; i < 100; ++i) (void)arena.create(i);
    EXPECT_EQ(Tracked::live.size(), 100u);
  }
  EXPECT_TRUE(Tracked::live.empty());
  EXPECT_EQ(Tracked::constructed, Tracked::destroyed);
  EXPECT_EQ(Tracked::bad_destroys, 0);
}

TEST(Arena, HoldsMoveOnlyValues) {
  Arena<std::unique_ptr<int>> arena;
  const auto a = arena.create(std::make_unique<int>(1));
  const auto b = arena.create(std::make_unique<int>(2));
  const auto c = arena.create(std::make_unique<int>(3));
  arena.erase(a);
  EXPECT_EQ(*arena.get(b), 2);
  EXPECT_EQ(*arena.get(c), 3);
}

TEST(Arena, ThrowingConstructorLeavesArenaUnchanged) {
  Arena<MaybeThrows> arena;
  EXPECT_THROW((void)arena.create(true), std::runtime_error);
  EXPECT_EQ(arena.size(), 0u);
  EXPECT_EQ(arena.slot_count(), 0u);

  const auto a = arena.create(false);
  const auto b = arena.create(false);
  arena.erase(a);
  EXPECT_THROW((void)arena.create(true), std::runtime_error);
  EXPECT_EQ(arena.size(), 1u);
  EXPECT_TRUE(arena.contains(b));
  EXPECT_FALSE(arena.contains(a));
  // The erased slot is still on the free list and is reused with a fresh generation.
  const auto c = arena.create(false);
  EXPECT_EQ(c.index(), a.index());
  EXPECT_NE(c, a);
  EXPECT_EQ(arena.slot_count(), 2u);
  for (int i = 0; i < 1000; ++i) {
    EXPECT_THROW((void)arena.create(true), std::runtime_error);
  }
  EXPECT_EQ(arena.slot_count(), 2u) << "failed creates must not leak slots";
}

// Exhausting 2^32 generations through Arena takes tens of seconds; run it with
// --gtest_also_run_disabled_tests. SlotTable tests below cover the logic quickly.
TEST(Arena, DISABLED_GenerationExhaustionRetiresSlotFullCycle) {
  Arena<uint32_t> arena;
  Handle<uint32_t> h = arena.create(0u);
  const Handle<uint32_t> first = h;
  for (uint64_t g = 0; g + 1 < detail::kMaxGeneration; ++g) {
    arena.erase(h);
    h = arena.create(0u);
    if (h.index() != first.index()) FAIL() << "slot moved early at generation " << g;
  }
  EXPECT_EQ(h.generation(), detail::kMaxGeneration - 1);
  arena.erase(h);
  const auto next = arena.create(0u);
  EXPECT_NE(next.index(), first.index()) << "exhausted slot must be retired";
  EXPECT_EQ(arena.slot_count(), 2u);
  EXPECT_FALSE(arena.contains(first));
  EXPECT_FALSE(arena.contains(h));
}

// ---------------------------------------------------------------------------------------
// SlotTable: generation exhaustion, with generations set close to the limit.

TEST(SlotTable, ExhaustedGenerationRetiresSlot) {
  detail::SlotTable table;
  const uint32_t index = table.acquire();
  table[index].generation = detail::kMaxGeneration - 2;
  table[index].payload = 0;
  ASSERT_TRUE(table.live(index, detail::kMaxGeneration - 2));

  // The last usable generation is still handed out.
  table.release(index);
  EXPECT_FALSE(table.live(index, detail::kMaxGeneration - 2));
  EXPECT_EQ(table.free_count(), 1u);
  EXPECT_EQ(table.acquire(), index);
  EXPECT_EQ(table[index].generation, detail::kMaxGeneration - 1);
  table[index].payload = 0;
  EXPECT_TRUE(table.live(index, detail::kMaxGeneration - 1));

  // Releasing it retires the slot: not on the free list, never live again.
  table.release(index);
  EXPECT_EQ(table.free_count(), 0u);
  EXPECT_FALSE(table.live(index, detail::kMaxGeneration - 1));
  EXPECT_FALSE(table.live(index, detail::kMaxGeneration));
  const uint32_t next = table.acquire();
  EXPECT_NE(next, index);
  EXPECT_EQ(table.slot_count(), 2u);
  EXPECT_EQ(table[next].generation, 0u);
}

TEST(SlotTable, ClearRetiresExhaustedSlots) {
  detail::SlotTable table;
  const uint32_t live_last = table.acquire();  // live at the last usable generation
  const uint32_t free_last = table.acquire();  // free, next generation is the last
  const uint32_t retired = table.acquire();    // already retired
  const uint32_t ordinary = table.acquire();
  table[live_last] = {detail::kMaxGeneration - 1, 0};
  table[free_last] = {detail::kMaxGeneration - 2, 0};
  table[retired] = {detail::kMaxGeneration - 1, 0};
  table[ordinary] = {5, 0};
  table.release(free_last);
  table.release(retired);
  EXPECT_EQ(table.free_count(), 1u);

  table.clear();
  EXPECT_EQ(table[ordinary].generation, 6u);
  EXPECT_FALSE(table.live(ordinary, 5));
  EXPECT_FALSE(table.live(live_last, detail::kMaxGeneration - 1));
  // Only the ordinary slot survives; the free_last slot would have been handed out at
  // generation kMax - 1, but clear() bumps every slot, so it is retired too.
  EXPECT_EQ(table.free_count(), 1u);
  EXPECT_EQ(table.acquire(), ordinary);
  EXPECT_EQ(table.acquire(), 4u) << "next acquire must be a new slot";
}

TEST(SlotTable, ReleaseBumpsGenerationAndRecyclesLifo) {
  detail::SlotTable table;
  const uint32_t a = table.acquire();
  const uint32_t b = table.acquire();
  table[a].payload = 0;
  table[b].payload = 0;
  table.release(a);
  table.release(b);
  EXPECT_EQ(table[a].generation, 1u);
  EXPECT_EQ(table[b].generation, 1u);
  EXPECT_EQ(table.acquire(), b);
  EXPECT_EQ(table.acquire(), a);
  EXPECT_EQ(table.slot_count(), 2u);
}

// ---------------------------------------------------------------------------------------
// StableArena

TEST(StableArena, CreateGetErase) {
  StableArena<Point> arena;
  const auto a = arena.create(Point{1, 1.0});
  const auto b = arena.create(Point{2, 2.0});
  EXPECT_EQ(arena.size(), 2u);
  EXPECT_EQ(arena.get(a).id, 1u);
  EXPECT_EQ(std::as_const(arena).get(b).id, 2u);
  EXPECT_TRUE(arena.erase(a));
  EXPECT_FALSE(arena.contains(a));
  EXPECT_EQ(arena.try_get(a), nullptr);
  EXPECT_EQ(std::as_const(arena).try_get(a), nullptr);
  ExpectGetThrowsNaming(arena, a);
  EXPECT_FALSE(arena.erase(a));
  EXPECT_EQ(arena.size(), 1u);

  const auto c = arena.create(Point{3, 3.0});
  EXPECT_EQ(c.index(), a.index());
  EXPECT_NE(c, a);
  EXPECT_FALSE(arena.contains(a));
  EXPECT_EQ(arena.get(c).id, 3u);
}

TEST(StableArena, NullHandleIsNeverContained) {
  StableArena<Point> arena;
  (void)arena.create();
  EXPECT_FALSE(arena.contains(Handle<Point>::null()));
  EXPECT_EQ(arena.try_get(Handle<Point>::null()), nullptr);
  EXPECT_FALSE(arena.erase(Handle<Point>::null()));
  ExpectGetThrowsNaming(arena, Handle<Point>::null());
  ExpectGetThrowsNaming(arena, Handle<Point>(5000, 0));
}

TEST(StableArena, ErrorMessageNamesTheHandle) {
  StableArena<Point> arena;
  const auto h = arena.create();
  arena.erase(h);
  try {
    (void)arena.get(h);
    FAIL();
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("StableArena"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("Handle(0v0)"), std::string::npos) << e.what();
  }
}

TEST(StableArena, AddressesStayStableUnderChurn) {
  StableArena<Point, 64> arena;
  std::vector<std::pair<Handle<Point>, const Point*>> anchors;
  for (uint64_t i = 0; i < 20; ++i) {
    const auto h = arena.create(Point{1'000'000 + i, double(i)});
    anchors.emplace_back(h, &arena.get(h));
  }
  std::vector<Handle<Point>> others;
  std::mt19937 rng(3);
  uint64_t next_id = 0;
  for (int op = 0; op < 100'000; ++op) {
    // Grow to a few thousand (many pages), then drain, twice over.
    const bool growing = (op / 25'000) % 2 == 0;
    if (others.empty() || rng() % 100 < (growing ? 60u : 40u)) {
      others.push_back(arena.create(Point{next_id++, 0.0}));
    } else {
      const size_t k = rng() % others.size();
      ASSERT_TRUE(arena.erase(others[k]));
      others[k] = others.back();
      others.pop_back();
    }
  }
  EXPECT_GT(arena.slot_count(), 64u * 10) << "churn should have spanned many pages";
  for (uint64_t i = 0; i < anchors.size(); ++i) {
    const auto& [h, address] = anchors[i];
    ASSERT_TRUE(arena.contains(h));
    EXPECT_EQ(&arena.get(h), address);
    EXPECT_EQ(address->id, 1'000'000 + i);
    EXPECT_EQ(address->x, double(i));
  }
}

TEST(StableArena, ChurnReusesSlots) {
  StableArena<Point> arena;
  std::vector<Handle<Point>> live;
  for (uint64_t i = 0; i < 300; ++i) live.push_back(arena.create(Point{i}));
  std::mt19937 rng(11);
  for (int cycle = 0; cycle < 100'000; ++cycle) {
    const size_t k = rng() % live.size();
    const auto old = live[k];
    ASSERT_TRUE(arena.erase(old));
    live[k] = arena.create(Point{uint64_t(cycle)});
    ASSERT_NE(live[k], old);
    ASSERT_FALSE(arena.contains(old));
  }
  EXPECT_EQ(arena.size(), 300u);
  EXPECT_EQ(arena.slot_count(), 300u);
}

TEST(StableArena, DestructorsRunExactlyOnce) {
  Tracked::Reset();
  {
    StableArena<Tracked, 16> arena;
    std::vector<Handle<Tracked>> handles;
    for (int i = 0; i < 1000; ++i) handles.push_back(arena.create(i));
    EXPECT_EQ(Tracked::constructed, 1000) << "values are built in place, never moved";
    for (int i = 0; i < 1000; i += 2) arena.erase(handles[i]);
    EXPECT_EQ(Tracked::live.size(), 500u);
    arena.for_each([&](Handle<Tracked> h, Tracked& t) {
      if (t.value % 3 == 0) arena.erase(h);
    });
    EXPECT_EQ(Tracked::live.size(), arena.size());
    for (int i = 0; i < 200; ++i) (void)arena.create(i);  // reuse slots
    EXPECT_EQ(Tracked::live.size(), arena.size());
    arena.clear();
    EXPECT_TRUE(Tracked::live.empty());
    EXPECT_EQ(arena.size(), 0u);
    for (int i = 0; i < 77; ++i) (void)arena.create(i);
  }
  EXPECT_TRUE(Tracked::live.empty());
  EXPECT_EQ(Tracked::constructed, Tracked::destroyed);
  EXPECT_EQ(Tracked::bad_destroys, 0);
}

TEST(StableArena, MoveTransfersOwnershipWithoutDoubleDestroy) {
  Tracked::Reset();
  {
    StableArena<Tracked> source;
    const auto h = source.create(42);
    const Tracked* address = &source.get(h);

    StableArena<Tracked> moved(std::move(source));
    EXPECT_EQ(moved.size(), 1u);
    EXPECT_EQ(&moved.get(h), address) << "moving the arena does not move the values";
    EXPECT_EQ(source.size(), 0u);  // NOLINT(bugprone-use-after-move): documented empty
    EXPECT_FALSE(source.contains(h));

    StableArena<Tracked> target;
    for (int i = 0; i < 10; ++i) (void)target.create(i);
    target = std::move(moved);  // the 10 values target held must be destroyed
    EXPECT_EQ(Tracked::live.size(), 1u);
    EXPECT_EQ(target.size(), 1u);
    EXPECT_EQ(target.get(h).value, 42);
    EXPECT_EQ(moved.size(), 0u);  // NOLINT(bugprone-use-after-move)

    // A moved-from arena is empty and usable.
    const auto again = source.create(7);
    EXPECT_EQ(source.get(again).value, 7);
  }
  EXPECT_TRUE(Tracked::live.empty());
  EXPECT_EQ(Tracked::constructed, Tracked::destroyed);
  EXPECT_EQ(Tracked::bad_destroys, 0);
}

TEST(StableArena, ForEachMayEraseCurrent) {
  StableArena<Point, 8> arena;
  std::vector<Handle<Point>> handles;
  for (uint64_t i = 0; i < 100; ++i) handles.push_back(arena.create(Point{i}));
  for (uint64_t i = 0; i < 100; i += 10) arena.erase(handles[i]);  // holes are skipped

  std::vector<uint64_t> visited;
  arena.for_each([&](Handle<Point> h, Point& p) {
    EXPECT_EQ(&arena.get(h), &p);
    visited.push_back(p.id);
    if (p.id % 2 == 1) {
      EXPECT_TRUE(arena.erase(h));
    }
  });
  ASSERT_EQ(visited.size(), 90u);
  EXPECT_TRUE(std::is_sorted(visited.begin(), visited.end())) << "slot order";
  EXPECT_EQ(arena.size(), 40u);
  for (uint64_t i = 0; i < 100; ++i) {
    EXPECT_EQ(arena.contains(handles[i]), i % 2 == 0 && i % 10 != 0) << i;
  }
  size_t count = 0;
  arena.for_each([&](Handle<Point>, Point& p) {
    EXPECT_EQ(p.id % 2, 0u);
    ++count;
  });
  EXPECT_EQ(count, 40u);
}

TEST(StableArena, ClearInvalidatesOldHandles) {
  StableArena<Point> arena;
  std::vector<Handle<Point>> old;
  for (uint64_t i = 0; i < 600; ++i) old.push_back(arena.create(Point{i}));
  arena.clear();
  EXPECT_TRUE(arena.empty());
  for (const auto& h : old) {
    EXPECT_FALSE(arena.contains(h));
    EXPECT_EQ(arena.try_get(h), nullptr);
  }
  size_t visited = 0;
  arena.for_each([&](Handle<Point>, Point&) { ++visited; });
  EXPECT_EQ(visited, 0u);
  std::unordered_set<Handle<Point>> old_set(old.begin(), old.end());
  for (uint64_t i = 0; i < 600; ++i) EXPECT_EQ(old_set.count(arena.create(Point{i})), 0u);
  EXPECT_EQ(arena.slot_count(), 600u);
  for (const auto& h : old) EXPECT_FALSE(arena.contains(h));
}

TEST(StableArena, ThrowingConstructorLeavesArenaUnchanged) {
  StableArena<MaybeThrows> arena;
  EXPECT_THROW((void)arena.create(true), std::runtime_error);
  EXPECT_EQ(arena.size(), 0u);
  EXPECT_EQ(arena.slot_count(), 0u);
  const auto a = arena.create(false);
  arena.erase(a);
  for (int i = 0; i < 100; ++i) EXPECT_THROW((void)arena.create(true), std::runtime_error);
  const auto b = arena.create(false);
  EXPECT_EQ(b.index(), a.index());
  EXPECT_NE(b, a);
  EXPECT_EQ(arena.slot_count(), 1u) << "failed creates must not leak slots";
  size_t visited = 0;
  arena.for_each([&](Handle<MaybeThrows>, MaybeThrows&) { ++visited; });
  EXPECT_EQ(visited, 1u);
}

}  // namespace
}  // namespace flatslam
