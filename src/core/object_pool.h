// A pool of reusable scratch objects for concurrent callers: Acquire() hands out an idle object
// (or a new one) and the lease gives it back. Buffers inside keep their capacity between uses,
// so a steady stream of frames stops allocating after the first few: no allocator churn, no
// page faults, a flat resident set.
// Concurrency: Acquire() and lease release are thread-safe (one short mutex section each).
#pragma once

#include <memory>
#include <mutex>
#include <utility>
#include <vector>

namespace flatslam {

template <class T>
class ObjectPool {
 public:
  class Lease {
   public:
    Lease(ObjectPool* pool, std::unique_ptr<T> object) : pool_(pool), object_(std::move(object)) {}
    Lease(Lease&&) noexcept = default;
    Lease& operator=(Lease&&) = delete;
    Lease(const Lease&) = delete;
    ~Lease() {
      if (object_) pool_->Release(std::move(object_));
    }
    [[nodiscard]] T& operator*() const { return *object_; }
    [[nodiscard]] T* operator->() const { return object_.get(); }
    [[nodiscard]] T* get() const { return object_.get(); }

   private:
    ObjectPool* pool_;
    std::unique_ptr<T> object_;
  };

  [[nodiscard]] Lease Acquire() {
    {
      std::lock_guard<std::mutex> lock(mutex_);
      if (!idle_.empty()) {
        std::unique_ptr<T> object = std::move(idle_.back());
        idle_.pop_back();
        return Lease(this, std::move(object));
      }
    }
    return Lease(this, std::make_unique<T>());
  }
  // Objects created so far and not in use (for tests).
  [[nodiscard]] size_t idle() const {
    std::lock_guard<std::mutex> lock(mutex_);
    return idle_.size();
  }

 private:
  void Release(std::unique_ptr<T> object) {
    std::lock_guard<std::mutex> lock(mutex_);
    idle_.push_back(std::move(object));
  }

  mutable std::mutex mutex_;
  std::vector<std::unique_ptr<T>> idle_;
};

}  // namespace flatslam
