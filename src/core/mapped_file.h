// A regular file mapped read-only into memory, unmapped when the owner goes: how map snapshots and
// the vocabulary are read in place.
// Concurrency: a move-only value; its bytes may be read from any thread while it lives.
#pragma once

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <span>
#include <string>
#include <utility>

#include "core/error.h"

namespace flatslam {

class MappedFile {
 public:
  MappedFile() = default;
  MappedFile(MappedFile&& other) noexcept { *this = std::move(other); }
  MappedFile& operator=(MappedFile&& other) noexcept {
    if (this != &other) {
      Unmap();
      data_ = std::exchange(other.data_, nullptr);
      size_ = std::exchange(other.size_, 0);
    }
    return *this;
  }
  MappedFile(const MappedFile&) = delete;
  MappedFile& operator=(const MappedFile&) = delete;
  ~MappedFile() { Unmap(); }

  // Maps `path`. Errors start with `what` (e.g. "map snapshot 'F'") and say what failed: "cannot
  // open (...)", "not a regular file", "truncated (N bytes)" below min_size, "cannot mmap (...)".
  // populate: read the whole file in now (MAP_POPULATE) rather than page by page on first touch.
  [[nodiscard]] static MappedFile Open(const std::filesystem::path& path, const std::string& what, size_t min_size,
                                       bool populate = false) {
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    FLATSLAM_CHECK(fd >= 0, what, ": cannot open (", std::strerror(errno), ")");
    struct Closer {
      int fd;
      ~Closer() { ::close(fd); }
    } closer{fd};
    struct stat st {};
    FLATSLAM_CHECK(::fstat(fd, &st) == 0, what, ": cannot stat (", std::strerror(errno), ")");
    FLATSLAM_CHECK(S_ISREG(st.st_mode), what, ": not a regular file");
    const size_t size = static_cast<size_t>(st.st_size);
    FLATSLAM_CHECK(size >= min_size && size > 0, what, ": truncated (", size, " bytes)");
    void* data = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE | (populate ? MAP_POPULATE : 0), fd, 0);
    FLATSLAM_CHECK(data != MAP_FAILED, what, ": cannot mmap (", std::strerror(errno), ")");
    MappedFile file;
    file.data_ = data;
    file.size_ = size;
    return file;
  }

  [[nodiscard]] std::span<const uint8_t> bytes() const { return {static_cast<const uint8_t*>(data_), size_}; }
  [[nodiscard]] bool empty() const { return data_ == nullptr; }

 private:
  void Unmap() {
    if (data_ != nullptr) ::munmap(data_, size_);
    data_ = nullptr;
    size_ = 0;
  }
  void* data_ = nullptr;
  size_t size_ = 0;
};

}  // namespace flatslam
