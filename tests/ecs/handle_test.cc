#include "ecs/handle.h"

#include <algorithm>
#include <concepts>
#include <cstdint>
#include <map>
#include <sstream>
#include <string>
#include <type_traits>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

struct KeyFrame {};
struct MapPoint {};

using KeyFrameHandle = Handle<KeyFrame>;
using MapPointHandle = Handle<MapPoint>;

// Handles of different entity types are unrelated types: no conversion, construction,
// assignment or comparison across them.
static_assert(!std::is_convertible_v<KeyFrameHandle, MapPointHandle>);
static_assert(!std::is_convertible_v<MapPointHandle, KeyFrameHandle>);
static_assert(!std::is_constructible_v<MapPointHandle, KeyFrameHandle>);
static_assert(!std::is_assignable_v<MapPointHandle&, KeyFrameHandle>);
static_assert(!std::equality_comparable_with<KeyFrameHandle, MapPointHandle>);
static_assert(!std::totally_ordered_with<KeyFrameHandle, MapPointHandle>);
// Neither raw integers nor bool slip in or out implicitly.
static_assert(!std::is_convertible_v<uint64_t, KeyFrameHandle>);
static_assert(!std::is_convertible_v<uint32_t, KeyFrameHandle>);
static_assert(!std::is_convertible_v<KeyFrameHandle, bool>);
static_assert(!std::is_convertible_v<KeyFrameHandle, uint64_t>);
// A handle is a plain 8-byte value.
static_assert(sizeof(KeyFrameHandle) == 8);
static_assert(std::is_trivially_copyable_v<KeyFrameHandle>);
static_assert(std::is_nothrow_default_constructible_v<KeyFrameHandle>);
// Accessors are usable in constant expressions.
static_assert(KeyFrameHandle(3, 7).index() == 3);
static_assert(KeyFrameHandle(3, 7).generation() == 7);
static_assert(KeyFrameHandle().is_null());
static_assert(KeyFrameHandle::from_packed(KeyFrameHandle(5, 9).packed()) == KeyFrameHandle(5, 9));

std::string ToString(const KeyFrameHandle& h) {
  std::ostringstream out;
  out << h;
  return out.str();
}

TEST(Handle, DefaultIsNull) {
  const KeyFrameHandle h;
  EXPECT_TRUE(h.is_null());
  EXPECT_FALSE(static_cast<bool>(h));
  EXPECT_EQ(h, KeyFrameHandle::null());
  EXPECT_EQ(h.index(), KeyFrameHandle::kNullIndex);
  EXPECT_EQ(h.generation(), 0u);
}

TEST(Handle, ValidHandleIsNotNull) {
  const KeyFrameHandle h(0, 0);
  EXPECT_FALSE(h.is_null());
  EXPECT_TRUE(static_cast<bool>(h));
  EXPECT_NE(h, KeyFrameHandle::null());
  EXPECT_EQ(h.index(), 0u);
  EXPECT_EQ(h.generation(), 0u);
}

TEST(Handle, EqualityComparesIndexAndGeneration) {
  EXPECT_EQ(KeyFrameHandle(4, 2), KeyFrameHandle(4, 2));
  EXPECT_NE(KeyFrameHandle(4, 2), KeyFrameHandle(4, 3));
  EXPECT_NE(KeyFrameHandle(4, 2), KeyFrameHandle(5, 2));
}

TEST(Handle, PackedRoundTrip) {
  const std::vector<KeyFrameHandle> handles = {KeyFrameHandle(0, 0), KeyFrameHandle(1, 0), KeyFrameHandle(0, 1),
                                               KeyFrameHandle(0xfffffffeu, 0xffffffffu), KeyFrameHandle::null()};
  for (const auto& h : handles) {
    EXPECT_EQ(KeyFrameHandle::from_packed(h.packed()), h) << h;
  }
  EXPECT_EQ(KeyFrameHandle(7, 3).packed(), (uint64_t{3} << 32) | 7u);
}

TEST(Handle, OrdersByIndexThenGeneration) {
  EXPECT_LT(KeyFrameHandle(1, 9), KeyFrameHandle(2, 0));
  EXPECT_LT(KeyFrameHandle(2, 0), KeyFrameHandle(2, 1));
  EXPECT_GT(KeyFrameHandle(3, 0), KeyFrameHandle(2, 5));
  EXPECT_LE(KeyFrameHandle(2, 1), KeyFrameHandle(2, 1));
  // The null handle has the largest index, so it sorts last.
  EXPECT_LT(KeyFrameHandle(0xfffffffeu, 0xffffffffu), KeyFrameHandle::null());

  std::vector<KeyFrameHandle> handles = {KeyFrameHandle(2, 1), KeyFrameHandle::null(), KeyFrameHandle(0, 5),
                                         KeyFrameHandle(2, 0), KeyFrameHandle(1, 1)};
  std::sort(handles.begin(), handles.end());
  const std::vector<KeyFrameHandle> expected = {KeyFrameHandle(0, 5), KeyFrameHandle(1, 1), KeyFrameHandle(2, 0),
                                                KeyFrameHandle(2, 1), KeyFrameHandle::null()};
  EXPECT_EQ(handles, expected);
}

TEST(Handle, PrintsIndexAndGeneration) {
  EXPECT_EQ(ToString(KeyFrameHandle(3, 7)), "Handle(3v7)");
  EXPECT_EQ(ToString(KeyFrameHandle(0, 0)), "Handle(0v0)");
  EXPECT_EQ(ToString(KeyFrameHandle::null()), "Handle(null)");
}

TEST(Handle, EqualHandlesHashEqual) {
  const std::hash<KeyFrameHandle> hash;
  EXPECT_EQ(hash(KeyFrameHandle(12, 4)), hash(KeyFrameHandle(12, 4)));
}

TEST(Handle, DistinctHandlesHashDistinct) {
  // Same index with many generations, and many indices with the same generation: the
  // slots a churning arena produces. The finalizer is a bijection on 64 bits.
  const std::hash<KeyFrameHandle> hash;
  std::unordered_set<size_t> hashes;
  size_t count = 0;
  for (uint32_t i = 0; i < 300; ++i) {
    for (uint32_t g = 0; g < 300; ++g) {
      hashes.insert(hash(KeyFrameHandle(i, g)));
      ++count;
    }
  }
  EXPECT_EQ(hashes.size(), count);
  // Low bits are spread too, which is what bucket selection uses.
  std::unordered_set<size_t> low_bits;
  for (uint32_t g = 0; g < 1024; ++g) low_bits.insert(hash(KeyFrameHandle(0, g)) & 1023u);
  EXPECT_GT(low_bits.size(), 500u);
}

TEST(Handle, WorksAsHashAndOrderedMapKey) {
  std::unordered_map<KeyFrameHandle, int> hashed;
  std::map<KeyFrameHandle, int> ordered;
  for (uint32_t i = 0; i < 100; ++i) {
    hashed[KeyFrameHandle(i, i % 3)] = static_cast<int>(i);
    ordered[KeyFrameHandle(i, i % 3)] = static_cast<int>(i);
  }
  EXPECT_EQ(hashed.size(), 100u);
  EXPECT_EQ(ordered.size(), 100u);
  EXPECT_EQ(hashed.at(KeyFrameHandle(42, 0)), 42);
  EXPECT_EQ(hashed.count(KeyFrameHandle(42, 1)), 0u);
  EXPECT_EQ(ordered.begin()->first, KeyFrameHandle(0, 0));
}

}  // namespace
}  // namespace flatslam
