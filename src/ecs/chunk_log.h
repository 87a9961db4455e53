// Append-only storage in fixed-size chunks that never move once allocated. One writer appends;
// a reader takes a View (the chunks and the count) while appends are excluded (on the writer's
// thread or under the lock that orders them) and then reads those elements without it: later
// appends write only past the view's count, and no chunk a view holds moves or is freed.
//
// With spilling on (SpillToFile()), a long log keeps only its last two chunks in memory: each
// older full chunk is written to an unlinked temporary file and freed, and reads of it go to
// the file. Memory then stays flat however long the log grows (a session's per-frame records).
// A chunk that cannot be written stays in memory: nothing is lost, only the memory is not saved.
// Concurrency: as above; the log itself is not thread-safe; views read the file with pread,
// which runs beside the writer's appends.
#pragma once

#include <cerrno>
#include <cstddef>
#include <algorithm>
#include <cstdio>
#include <memory>
#include <type_traits>
#include <vector>

#include <unistd.h>

#include "core/error.h"

namespace flatslam {

namespace detail {
// An unlinked temporary file that lives while a log or one of its views uses it.
class SpillFile {
 public:
  SpillFile() : file_(std::tmpfile()) {}
  ~SpillFile() {
    if (file_) std::fclose(file_);
  }
  SpillFile(const SpillFile&) = delete;
  SpillFile& operator=(const SpillFile&) = delete;
  [[nodiscard]] bool ok() const { return file_ != nullptr; }
  // Writes size bytes at offset; false on any failure (the caller keeps the data).
  bool Write(const void* data, size_t size, size_t offset) const {
    const char* p = static_cast<const char*>(data);
    while (size > 0) {
      const ssize_t n = ::pwrite(fileno(file_), p, size, static_cast<off_t>(offset));
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) return false;
      p += n, size -= static_cast<size_t>(n), offset += static_cast<size_t>(n);
    }
    return true;
  }
  void Read(void* data, size_t size, size_t offset) const {
    char* p = static_cast<char*>(data);
    while (size > 0) {
      const ssize_t n = ::pread(fileno(file_), p, size, static_cast<off_t>(offset));
      if (n < 0 && errno == EINTR) continue;
      FLATSLAM_CHECK(n > 0, "reading back spilled records from the temporary file failed at byte ", offset);
      p += n, size -= static_cast<size_t>(n), offset += static_cast<size_t>(n);
    }
  }

 private:
  std::FILE* file_;
};
}  // namespace detail

template <class T, size_t kChunk = 4096>
class ChunkLog {
  static_assert(std::is_trivially_copyable_v<T>, "spilled records are written as bytes");

 public:
  class View {
   public:
    [[nodiscard]] size_t size() const { return size_; }
    [[nodiscard]] bool empty() const { return size_ == 0; }
    // Calls f(element) for elements [begin, end) in order, reading spilled chunks a chunk at a time.
    template <class F>
    void ForEach(size_t begin, size_t end, F&& f) const {
      ForEachIn(chunks_, file_.get(), begin, end, f);
    }
    template <class F>
    void ForEach(F&& f) const {
      ForEach(0, size_, f);
    }

   private:
    friend class ChunkLog;
    std::vector<std::shared_ptr<const T[]>> chunks_;  // null: spilled
    std::shared_ptr<const detail::SpillFile> file_;
    size_t size_ = 0;
  };

  // Spill older chunks to a temporary file from now on. The file is made when the first chunk
  // spills (a short log never makes one); if it cannot be made, every chunk stays in memory.
  void SpillToFile() { spill_ = true; }

  void push_back(const T& value) {
    if (size_ == chunks_.size() * kChunk) {
      Spill();
      chunks_.push_back(std::shared_ptr<T[]>(new T[kChunk]));
    }
    Chunk(size_ / kChunk)[size_ % kChunk] = value;
    ++size_;
  }
  [[nodiscard]] size_t size() const { return size_; }
  [[nodiscard]] bool empty() const { return size_ == 0; }
  // Element i, read from the file when its chunk was spilled.
  [[nodiscard]] T operator[](size_t i) const {
    const auto& chunk = chunks_[i / kChunk];
    if (chunk) return chunk[i % kChunk];
    T value;
    file_->Read(&value, sizeof(T), i * sizeof(T));
    return value;
  }
  [[nodiscard]] T back() const { return (*this)[size_ - 1]; }
  // Chunks written to the file so far (tests, statistics).
  [[nodiscard]] size_t spilled_chunks() const { return spilled_; }

  template <class F>
  void ForEach(F&& f) const {
    ForEachIn(chunks_, file_.get(), 0, size_, f);
  }

  // Points *view at the elements so far (reusing its buffer): O(chunks), no element is copied.
  void TakeView(View* view) const {
    view->chunks_.assign(chunks_.begin(), chunks_.end());
    view->file_ = file_;
    view->size_ = size_;
  }

 private:
  T* Chunk(size_t c) { return const_cast<T*>(chunks_[c].get()); }

  // Before a new chunk starts: every full chunk but the newest goes to the file.
  void Spill() {
    if (!spill_ || chunks_.size() < 2) return;
    if (!file_) {
      auto file = std::make_shared<detail::SpillFile>();
      if (!file->ok()) {
        spill_ = false;
        return;
      }
      file_ = std::move(file);
    }
    while (chunks_.size() >= 2 && spilled_ < chunks_.size() - 1) {
      const size_t c = spilled_;
      if (!file_->Write(chunks_[c].get(), kChunk * sizeof(T), c * kChunk * sizeof(T))) {
        spill_ = false;  // no space left: keep every later chunk in memory
        return;
      }
      chunks_[c].reset();
      ++spilled_;
    }
  }

  template <class Chunks, class F>
  static void ForEachIn(const Chunks& chunks, const detail::SpillFile* file, size_t begin, size_t end, F& f) {
    std::unique_ptr<T[]> buffer;
    for (size_t i = begin; i < end;) {
      const size_t c = i / kChunk, offset = i % kChunk, n = std::min(end - i, kChunk - offset);
      if (const T* data = chunks[c].get()) {
        for (size_t k = 0; k < n; ++k) f(data[offset + k]);
      } else {
        if (!buffer) buffer.reset(new T[kChunk]);
        file->Read(buffer.get(), n * sizeof(T), i * sizeof(T));
        for (size_t k = 0; k < n; ++k) f(buffer[k]);
      }
      i += n;
    }
  }

  std::vector<std::shared_ptr<const T[]>> chunks_;  // null: spilled to file_
  std::shared_ptr<detail::SpillFile> file_;
  size_t size_ = 0, spilled_ = 0;
  bool spill_ = false;
};

}  // namespace flatslam
