#include "storage/line_log.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "core/error.h"

namespace flatslam {

LineLog::LineLog(const std::filesystem::path& path, std::string_view header, Mode mode,
                 std::chrono::milliseconds flush_interval)
    : path_(path), last_flush_(std::chrono::steady_clock::now()), interval_(flush_interval) {
  const int flags = O_WRONLY | O_CREAT | O_CLOEXEC | (mode == Mode::kAppend ? O_APPEND : O_TRUNC);
  fd_ = ::open(path.c_str(), flags, 0644);
  FLATSLAM_CHECK(fd_ >= 0, path.string(), ": cannot open for writing (", std::strerror(errno), ")");
  if (mode == Mode::kTruncate && !header.empty()) {
    buffer_.assign(header);
    Flush();
  }
}

LineLog::~LineLog() {
  if (fd_ < 0) return;
  Flush();
  ::close(fd_);
}

void LineLog::Append(std::string_view lines) {
  buffer_.append(lines);
  if (std::chrono::steady_clock::now() - last_flush_ >= interval_) Flush();
}

void LineLog::Flush() {
  last_flush_ = std::chrono::steady_clock::now();
  // One write per flush: the file only ever grows by whole lines (a short write is retried).
  size_t done = 0;
  while (done < buffer_.size() && !failed_) {
    const ssize_t n = ::write(fd_, buffer_.data() + done, buffer_.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0)
      failed_ = true;
    else
      done += static_cast<size_t>(n);
  }
  buffer_.clear();
}

void LineLog::Close() {
  if (fd_ < 0) return;
  Flush();
  const bool closed = ::close(fd_) == 0;
  fd_ = -1;
  FLATSLAM_CHECK(!failed_ && closed, path_.string(), ": write failed");
}

}  // namespace flatslam
