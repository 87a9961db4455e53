// Typed generational handles: a 32-bit slot index plus a 32-bit generation.
// Concurrency: plain values, freely copied between threads.
#pragma once

#include <compare>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <limits>
#include <ostream>

namespace flatslam {

// Refers to an entity of type T stored in an Arena<T> (or StableArena<T>).
// Handle<A> and Handle<B> are distinct types and never convert into each other.
template <class T>
class Handle {
 public:
  static constexpr uint32_t kNullIndex = std::numeric_limits<uint32_t>::max();

  constexpr Handle() = default;
  constexpr Handle(uint32_t index, uint32_t generation) : index_(index), generation_(generation) {}

  [[nodiscard]] static constexpr Handle null() { return Handle(); }
  [[nodiscard]] constexpr bool is_null() const { return index_ == kNullIndex; }
  [[nodiscard]] constexpr explicit operator bool() const { return !is_null(); }
  [[nodiscard]] constexpr uint32_t index() const { return index_; }
  [[nodiscard]] constexpr uint32_t generation() const { return generation_; }
  // Packs index (low) and generation (high) into one 64-bit value, e.g. for files and hashing.
  [[nodiscard]] constexpr uint64_t packed() const { return (uint64_t{generation_} << 32) | uint64_t{index_}; }
  [[nodiscard]] static constexpr Handle from_packed(uint64_t v) {
    return Handle(static_cast<uint32_t>(v & 0xffffffffu), static_cast<uint32_t>(v >> 32));
  }

  friend constexpr bool operator==(const Handle&, const Handle&) = default;
  friend constexpr auto operator<=>(const Handle&, const Handle&) = default;

  friend std::ostream& operator<<(std::ostream& out, const Handle& h) {
    if (h.is_null()) return out << "Handle(null)";
    return out << "Handle(" << h.index_ << "v" << h.generation_ << ")";
  }

 private:
  uint32_t index_ = kNullIndex;
  uint32_t generation_ = 0;
};

}  // namespace flatslam

template <class T>
struct std::hash<flatslam::Handle<T>> {
  size_t operator()(const flatslam::Handle<T>& h) const noexcept {
    // splitmix64 finalizer: spreads index and generation over all bits.
    uint64_t x = h.packed() + 0x9e3779b97f4a7c15ull;
    x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ull;
    x = (x ^ (x >> 27)) * 0x94d049bb133111ebull;
    return static_cast<size_t>(x ^ (x >> 31));
  }
};
