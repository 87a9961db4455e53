// Generational slot maps: Arena<T> keeps values packed for span iteration,
// StableArena<T> keeps every value at a fixed address.
// Concurrency: no internal locking; one writer or many readers, as the schedule grants.
#pragma once

#include <cassert>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <memory>
#include <new>
#include <span>
#include <type_traits>
#include <utility>
#include <vector>

#include "core/error.h"
#include "ecs/handle.h"

namespace flatslam {

namespace detail {
inline constexpr uint32_t kNoDense = std::numeric_limits<uint32_t>::max();
inline constexpr uint32_t kMaxGeneration = std::numeric_limits<uint32_t>::max();

// Slot bookkeeping shared by both arenas: generations and a LIFO free list.
// A slot whose generation is exhausted is retired instead of reused.
class SlotTable {
 public:
  struct Slot {
    uint32_t generation = 0;
    uint32_t payload = kNoDense;  // dense index (Arena) or kNoDense/0 alive flag (StableArena)
  };

  // Returns the index of a free slot (reused or new) with its current generation.
  [[nodiscard]] uint32_t acquire() {
    if (!free_.empty()) {
      const uint32_t index = free_.back();
      free_.pop_back();
      return index;
    }
    FLATSLAM_CHECK(slots_.size() < kNoDense, "arena is full (", slots_.size(), " slots)");
    slots_.push_back(Slot{});
    return static_cast<uint32_t>(slots_.size() - 1);
  }

  // Undoes the acquire() that returned index when building its value failed: the slot
  // goes back unused with its generation unchanged. A fresh slot is the last one and has
  // generation 0; a recycled slot always has generation >= 1 and returns to the free
  // list, whose capacity it just left (so this does not allocate).
  void cancel(uint32_t index) {
    if (index + 1 == slots_.size() && slots_[index].generation == 0) {
      slots_.pop_back();
    } else {
      free_.push_back(index);
    }
  }

  // Invalidates every handle to the slot and makes it reusable.
  void release(uint32_t index) {
    Slot& slot = slots_[index];
    slot.payload = kNoDense;
    if (slot.generation == kMaxGeneration - 1) {
      slot.generation = kMaxGeneration;  // retired: never handed out again
      return;
    }
    ++slot.generation;
    free_.push_back(index);
  }

  [[nodiscard]] bool live(uint32_t index, uint32_t generation) const {
    return index < slots_.size() && slots_[index].generation == generation && slots_[index].payload != kNoDense;
  }

  [[nodiscard]] Slot& operator[](uint32_t index) { return slots_[index]; }
  [[nodiscard]] const Slot& operator[](uint32_t index) const { return slots_[index]; }
  [[nodiscard]] size_t slot_count() const { return slots_.size(); }
  [[nodiscard]] size_t free_count() const { return free_.size(); }

  void reserve(size_t n) {
    slots_.reserve(n);
    free_.reserve(n);
  }
  void clear() {
    // Keep generations so that handles from before clear() stay stale.
    free_.clear();
    for (uint32_t i = static_cast<uint32_t>(slots_.size()); i-- > 0;) {
      if (slots_[i].payload != kNoDense) slots_[i].payload = kNoDense;
      if (slots_[i].generation == kMaxGeneration) continue;
      ++slots_[i].generation;
      if (slots_[i].generation == kMaxGeneration) continue;
      free_.push_back(i);
    }
  }

 private:
  std::vector<Slot> slots_;
  std::vector<uint32_t> free_;
};

template <class T>
[[noreturn]] void ThrowStale(const char* arena, Handle<T> h) {
  Fail(arena, ": stale or invalid ", h);
}
}  // namespace detail

// Packed slot map. Values live contiguously; erase swaps the last value into the hole,
// so references are invalidated by erase and create. Iterating handles() backwards
// while erasing the current element is safe; erase_if() is the usual way.
template <class T>
class Arena {
 public:
  using value_type = T;
  using handle_type = Handle<T>;

  // Strong guarantee: if T's constructor or an allocation throws, the arena is unchanged.
  template <class... Args>
  [[nodiscard]] Handle<T> create(Args&&... args) {
    const uint32_t index = slots_.acquire();
    const Handle<T> h(index, slots_[index].generation);
    bool handle_pushed = false;
    try {
      handles_.push_back(h);
      handle_pushed = true;
      values_.emplace_back(std::forward<Args>(args)...);
    } catch (...) {
      if (handle_pushed) handles_.pop_back();
      slots_.cancel(index);
      throw;
    }
    slots_[index].payload = static_cast<uint32_t>(values_.size() - 1);
    return h;
  }

  // Removes the entity; returns false (and does nothing) for a stale or null handle.
  bool erase(Handle<T> h) {
    if (!contains(h)) return false;
    const uint32_t dense = slots_[h.index()].payload;
    const uint32_t last = static_cast<uint32_t>(values_.size() - 1);
    if (dense != last) {
      values_[dense] = std::move(values_[last]);
      handles_[dense] = handles_[last];
      slots_[handles_[dense].index()].payload = dense;
    }
    values_.pop_back();
    handles_.pop_back();
    slots_.release(h.index());
    return true;
  }

  // Erases every entity for which pred(handle, value) is true; returns how many.
  template <class Pred>
  size_t erase_if(Pred&& pred) {
    size_t erased = 0;
    for (size_t i = values_.size(); i-- > 0;) {
      if (pred(handles_[i], values_[i])) {
        erase(handles_[i]);
        ++erased;
      }
    }
    return erased;
  }

  [[nodiscard]] bool contains(Handle<T> h) const { return slots_.live(h.index(), h.generation()); }

  [[nodiscard]] T* try_get(Handle<T> h) { return contains(h) ? &values_[slots_[h.index()].payload] : nullptr; }
  [[nodiscard]] const T* try_get(Handle<T> h) const {
    return contains(h) ? &values_[slots_[h.index()].payload] : nullptr;
  }
  // Checked access: throws flatslam::Error naming the handle when it is stale.
  [[nodiscard]] T& get(Handle<T> h) {
    if (T* v = try_get(h)) return *v;
    detail::ThrowStale("Arena", h);
  }
  [[nodiscard]] const T& get(Handle<T> h) const {
    if (const T* v = try_get(h)) return *v;
    detail::ThrowStale("Arena", h);
  }

  // Position of a live entity in values()/handles().
  [[nodiscard]] size_t dense_index(Handle<T> h) const {
    FLATSLAM_CHECK(contains(h), "Arena: stale or invalid ", h);
    return slots_[h.index()].payload;
  }

  [[nodiscard]] std::span<T> values() { return values_; }
  [[nodiscard]] std::span<const T> values() const { return values_; }
  [[nodiscard]] std::span<const Handle<T>> handles() const { return handles_; }

  [[nodiscard]] size_t size() const { return values_.size(); }
  [[nodiscard]] bool empty() const { return values_.empty(); }
  // Slots ever allocated (live + free); bounded when creates and erases balance.
  [[nodiscard]] size_t slot_count() const { return slots_.slot_count(); }
  [[nodiscard]] size_t capacity() const { return values_.capacity(); }

  void reserve(size_t n) {
    values_.reserve(n);
    handles_.reserve(n);
    slots_.reserve(n);
  }
  // Makes this arena a copy of `other` with the same handles; each value is copied by
  // copy(T& dst, const T& src) over whatever value was at that dense position before, so a
  // repeated copy can reuse buffers and skip what it knows to be unchanged.
  template <class Copy>
  void assign_from(const Arena& other, Copy&& copy) {
    values_.resize(other.values_.size());
    for (size_t i = 0; i < values_.size(); ++i) copy(values_[i], other.values_[i]);
    handles_ = other.handles_;
    slots_ = other.slots_;
  }
  void clear() {
    values_.clear();
    handles_.clear();
    slots_.clear();
  }

 private:
  std::vector<T> values_;
  std::vector<Handle<T>> handles_;
  detail::SlotTable slots_;
};

// Slot map with stable addresses: values live in fixed-size pages that are never moved,
// so a reference stays valid until its entity is erased. Iteration skips free slots.
template <class T, size_t kPageSize = 256>
class StableArena {
  static_assert(kPageSize > 0 && (kPageSize & (kPageSize - 1)) == 0, "page size: power of two");

 public:
  using value_type = T;
  using handle_type = Handle<T>;

  StableArena() = default;
  StableArena(const StableArena&) = delete;
  StableArena& operator=(const StableArena&) = delete;
  // Moving transfers the pages, so values keep their addresses; the source is left empty.
  StableArena(StableArena&& other) noexcept
      : pages_(std::move(other.pages_)), slots_(std::move(other.slots_)), size_(std::exchange(other.size_, 0)) {
    other.reset_moved_from();
  }
  // Destroys the values this arena held before taking over other's.
  StableArena& operator=(StableArena&& other) noexcept {
    if (this != &other) {
      destroy_all();
      pages_ = std::move(other.pages_);
      slots_ = std::move(other.slots_);
      size_ = std::exchange(other.size_, 0);
      other.reset_moved_from();
    }
    return *this;
  }
  ~StableArena() { destroy_all(); }

  // Strong guarantee: if T's constructor or an allocation throws, the arena is unchanged.
  template <class... Args>
  [[nodiscard]] Handle<T> create(Args&&... args) {
    const uint32_t index = slots_.acquire();
    try {
      if (index / kPageSize >= pages_.size()) pages_.push_back(std::make_unique<Page>());
      ::new (static_cast<void*>(address(index))) T(std::forward<Args>(args)...);
    } catch (...) {
      slots_.cancel(index);
      throw;
    }
    slots_[index].payload = 0;  // alive
    ++size_;
    return Handle<T>(index, slots_[index].generation);
  }

  bool erase(Handle<T> h) {
    if (!contains(h)) return false;
    std::destroy_at(address(h.index()));
    slots_.release(h.index());
    --size_;
    return true;
  }

  [[nodiscard]] bool contains(Handle<T> h) const { return slots_.live(h.index(), h.generation()); }
  [[nodiscard]] T* try_get(Handle<T> h) { return contains(h) ? address(h.index()) : nullptr; }
  [[nodiscard]] const T* try_get(Handle<T> h) const { return contains(h) ? address(h.index()) : nullptr; }
  [[nodiscard]] T& get(Handle<T> h) {
    if (T* v = try_get(h)) return *v;
    detail::ThrowStale("StableArena", h);
  }
  [[nodiscard]] const T& get(Handle<T> h) const {
    if (const T* v = try_get(h)) return *v;
    detail::ThrowStale("StableArena", h);
  }

  // Calls fn(handle, value) for every live entity in slot order. fn may erase the
  // entity it is given (but no other).
  template <class Fn>
  void for_each(Fn&& fn) {
    for (uint32_t i = 0; i < slots_.slot_count(); ++i) {
      if (slots_[i].payload == detail::kNoDense) continue;
      fn(Handle<T>(i, slots_[i].generation), *address(i));
    }
  }

  [[nodiscard]] size_t size() const { return size_; }
  [[nodiscard]] bool empty() const { return size_ == 0; }
  [[nodiscard]] size_t slot_count() const { return slots_.slot_count(); }

  void clear() {
    destroy_all();
    slots_.clear();
    size_ = 0;
  }

 private:
  struct Page {
    alignas(T) std::byte bytes[sizeof(T) * kPageSize];
  };

  [[nodiscard]] T* address(uint32_t index) const {
    auto* page = pages_[index / kPageSize].get();
    return std::launder(reinterpret_cast<T*>(page->bytes) + (index % kPageSize));
  }
  void destroy_all() {
    for (uint32_t i = 0; i < slots_.slot_count(); ++i) {
      if (slots_[i].payload != detail::kNoDense) std::destroy_at(address(i));
    }
  }
  // Moved-from containers are only "valid but unspecified"; make this one empty.
  void reset_moved_from() noexcept {
    pages_.clear();
    slots_ = detail::SlotTable();
  }

  std::vector<std::unique_ptr<Page>> pages_;
  detail::SlotTable slots_;
  size_t size_ = 0;
};

}  // namespace flatslam
