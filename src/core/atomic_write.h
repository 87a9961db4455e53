// Whole-file writes that never leave a half-written file in place of a complete one: the content
// goes to a temporary file in the same directory, is flushed and fsynced, then renamed over the
// target; the directory is fsynced so the rename survives a power cut. On any failure the previous
// file is untouched and the temporary removed.
// Concurrency: reentrant for distinct paths.
#pragma once

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <functional>
#include <string>

#include "core/error.h"

namespace flatslam {

// Calls fill(file) on a temporary file next to `path`, then moves it into place. Throws
// flatslam::Error naming `path` when the file cannot be written; an exception from fill leaves the
// previous file untouched too.
inline void WriteFileAtomically(const std::filesystem::path& path, const std::function<void(std::FILE*)>& fill) {
  std::filesystem::path temp = path;
  temp += ".tmp-" + std::to_string(::getpid());
  std::FILE* file = std::fopen(temp.c_str(), "w");
  FLATSLAM_CHECK(file != nullptr, path.string(), ": cannot open for writing (", std::strerror(errno), ")");
  bool ok = false;
  try {
    fill(file);
    ok = std::ferror(file) == 0 && std::fflush(file) == 0 && ::fsync(::fileno(file)) == 0;
  } catch (...) {
    std::fclose(file);
    std::filesystem::remove(temp);
    throw;
  }
  const int error = errno;
  ok = (std::fclose(file) == 0) && ok;
  if (!ok || std::rename(temp.c_str(), path.c_str()) != 0) {
    const int rename_error = errno;
    std::error_code ec;
    std::filesystem::remove(temp, ec);
    Fail(path.string(), ": write failed (", std::strerror(ok ? rename_error : error), ")");
  }
  const std::filesystem::path dir = path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  const int fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    (void)::fsync(fd);  // a failure here leaves a complete file: not an error
    ::close(fd);
  }
}

}  // namespace flatslam
