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

struct FrameTag {};  // two entity types (the names differ from the map's own)
struct PointTag {};

using FrameTagHandle = Handle<FrameTag>;
using PointTagHandle = Handle<PointTag>;

// Handles of different entity types are unrelated types: no conversion, construction,
// assignment or comparison across them.
static_assert(!std::is_convertible_v<FrameTagHandle, PointTagHandle>);
static_assert(!std::is_convertible_v<PointTagHandle, FrameTagHandle>);
static_assert(!std::is_constructible_v<PointTagHandle, FrameTagHandle>);
static_assert(!std::is_assignable_v<PointTagHandle&, FrameTagHandle>);
static_assert(!std::equality_comparable_with<FrameTagHandle, PointTagHandle>);
static_assert(!std::totally_ordered_with<FrameTagHandle, PointTagHandle>);
// Neither raw integers nor bool slip in or out implicitly.
static_assert(!std::is_convertible_v<uint64_t, FrameTagHandle>);
static_assert(!std::is_convertible_v<uint32_t, FrameTagHandle>);
static_assert(!std::is_convertible_v<FrameTagHandle, bool>);
static_assert(!std::is_convertible_v<FrameTagHandle, uint64_t>);
// A handle is a plain 8-byte value.
static_assert(sizeof(FrameTagHandle) == 8);
static_assert(std::is_trivially_copyable_v<FrameTagHandle>);
static_assert(std::is_nothrow_default_constructible_v<FrameTagHandle>);
// Accessors are usable in constant expressions.
static_assert(FrameTagHandle(3, 7).index() == 3);
static_assert(FrameTagHandle(3, 7).generation() == 7);
static_assert(FrameTagHandle().is_null());
static_assert(FrameTagHandle::from_packed(FrameTagHandle(5, 9).packed()) == FrameTagHandle(5, 9));

std::string ToString(const FrameTagHandle& h) {
  std::ostringstream out;
  out << h;
  return out.str();
}

TEST(Handle, DefaultIsNull) {
  const FrameTagHandle h;
  EXPECT_TRUE(h.is_null());
  EXPECT_FALSE(static_cast<bool>(h));
  EXPECT_EQ(h, FrameTagHandle::null());
  EXPECT_EQ(h.index(), FrameTagHandle::kNullIndex);
  EXPECT_EQ(h.generation(), 0u);
}

TEST(Handle, ValidHandleIsNotNull) {
  const FrameTagHandle h(0, 0);
  EXPECT_FALSE(h.is_null());
  EXPECT_TRUE(static_cast<bool>(h));
  EXPECT_NE(h, FrameTagHandle::null());
  EXPECT_EQ(h.index(), 0u);
  EXPECT_EQ(h.generation(), 0u);
}

TEST(Handle, EqualityComparesIndexAndGeneration) {
  EXPECT_EQ(FrameTagHandle(4, 2), FrameTagHandle(4, 2));
  EXPECT_NE(FrameTagHandle(4, 2), FrameTagHandle(4, 3));
  EXPECT_NE(FrameTagHandle(4, 2), FrameTagHandle(5, 2));
}

TEST(Handle, PackedRoundTrip) {
  const std::vector<FrameTagHandle> handles = {FrameTagHandle(0, 0), FrameTagHandle(1, 0), FrameTagHandle(0, 1),
                                               FrameTagHandle(0xfffffffeu, 0xffffffffu), FrameTagHandle::null()};
  for (const auto& h : handles) {
    EXPECT_EQ(FrameTagHandle::from_packed(h.packed()), h) << h;
  }
  EXPECT_EQ(FrameTagHandle(7, 3).packed(), (uint64_t{3} << 32) | 7u);
}

TEST(Handle, OrdersByIndexThenGeneration) {
  EXPECT_LT(FrameTagHandle(1, 9), FrameTagHandle(2, 0));
  EXPECT_LT(FrameTagHandle(2, 0), FrameTagHandle(2, 1));
  EXPECT_GT(FrameTagHandle(3, 0), FrameTagHandle(2, 5));
  EXPECT_LE(FrameTagHandle(2, 1), FrameTagHandle(2, 1));
  // The null handle has the largest index, so it sorts last.
  EXPECT_LT(FrameTagHandle(0xfffffffeu, 0xffffffffu), FrameTagHandle::null());

  std::vector<FrameTagHandle> handles = {FrameTagHandle(2, 1), FrameTagHandle::null(), FrameTagHandle(0, 5),
                                         FrameTagHandle(2, 0), FrameTagHandle(1, 1)};
  std::sort(handles.begin(), handles.end());
  const std::vector<FrameTagHandle> expected = {FrameTagHandle(0, 5), FrameTagHandle(1, 1), FrameTagHandle(2, 0),
                                                FrameTagHandle(2, 1), FrameTagHandle::null()};
  EXPECT_EQ(handles, expected);
}

TEST(Handle, PrintsIndexAndGeneration) {
  EXPECT_EQ(ToString(FrameTagHandle(3, 7)), "Handle(3v7)");
  EXPECT_EQ(ToString(FrameTagHandle(0, 0)), "Handle(0v0)");
  EXPECT_EQ(ToString(FrameTagHandle::null()), "Handle(null)");
}

TEST(Handle, EqualHandlesHashEqual) {
  const std::hash<FrameTagHandle> hash;
  EXPECT_EQ(hash(FrameTagHandle(12, 4)), hash(FrameTagHandle(12, 4)));
}

TEST(Handle, DistinctHandlesHashDistinct) {
  // Same index with many generations, and many indices with the same generation: the
  // slots a churning arena produces. The finalizer is a bijection on 64 bits.
  const std::hash<FrameTagHandle> hash;
  std::unordered_set<size_t> hashes;
  size_t count = 0;
  for (uint32_t i = 0; i < 300; ++i) {
    for (uint32_t g = 0; g < 300; ++g) {
      hashes.insert(hash(FrameTagHandle(i, g)));
      ++count;
    }
  }
  EXPECT_EQ(hashes.size(), count);
  // Low bits are spread too, which is what bucket selection uses.
  std::unordered_set<size_t> low_bits;
  for (uint32_t g = 0; g < 1024; ++g) low_bits.insert(hash(FrameTagHandle(0, g)) & 1023u);
  EXPECT_GT(low_bits.size(), 500u);
}

TEST(Handle, WorksAsHashAndOrderedMapKey) {
  std::unordered_map<FrameTagHandle, int> hashed;
  std::map<FrameTagHandle, int> ordered;
  for (uint32_t i = 0; i < 100; ++i) {
    hashed[FrameTagHandle(i, i % 3)] = static_cast<int>(i);
    ordered[FrameTagHandle(i, i % 3)] = static_cast<int>(i);
  }
  EXPECT_EQ(hashed.size(), 100u);
  EXPECT_EQ(ordered.size(), 100u);
  EXPECT_EQ(hashed.at(FrameTagHandle(42, 0)), 42);
  EXPECT_EQ(hashed.count(FrameTagHandle(42, 1)), 0u);
  EXPECT_EQ(ordered.begin()->first, FrameTagHandle(0, 0));
}

}  // namespace
}  // namespace flatslam
