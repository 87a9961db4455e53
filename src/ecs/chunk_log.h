// Append-only storage in fixed-size chunks that never move once allocated. One writer appends;
// a reader takes a View (the chunk addresses and the count) while appends are excluded (on the
// writer's thread or under the lock that orders them) and then reads those elements without it:
// later appends write only past the view's count, and no chunk moves or is freed.
// Concurrency: as above; the log itself is not thread-safe.
#pragma once

#include <cstddef>
#include <memory>
#include <vector>

namespace flatslam {

template <class T, size_t kChunk = 4096>
class ChunkLog {
 public:
  class View {
   public:
    [[nodiscard]] size_t size() const { return size_; }
    [[nodiscard]] bool empty() const { return size_ == 0; }
    [[nodiscard]] const T& operator[](size_t i) const { return chunks_[i / kChunk][i % kChunk]; }

   private:
    friend class ChunkLog;
    std::vector<const T*> chunks_;
    size_t size_ = 0;
  };

  void push_back(const T& value) {
    if (size_ == chunks_.size() * kChunk) chunks_.push_back(std::make_unique<T[]>(kChunk));
    chunks_[size_ / kChunk][size_ % kChunk] = value;
    ++size_;
  }
  [[nodiscard]] size_t size() const { return size_; }
  [[nodiscard]] bool empty() const { return size_ == 0; }
  [[nodiscard]] const T& operator[](size_t i) const { return chunks_[i / kChunk][i % kChunk]; }
  [[nodiscard]] const T& back() const { return (*this)[size_ - 1]; }

  // Points *view at the elements so far (reusing its buffer): O(chunks), no element is copied.
  void TakeView(View* view) const {
    view->chunks_.resize(chunks_.size());
    for (size_t c = 0; c < chunks_.size(); ++c) view->chunks_[c] = chunks_[c].get();
    view->size_ = size_;
  }

 private:
  std::vector<std::unique_ptr<T[]>> chunks_;
  size_t size_ = 0;
};

}  // namespace flatslam
