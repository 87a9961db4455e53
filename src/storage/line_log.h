// A text file that grows by whole lines while a session runs (streamed trajectory, per-frame
// statistics): lines are buffered and handed to the OS in one write of complete lines at least
// every flush interval, so a process killed at any moment (even by SIGKILL) leaves a prefix of
// whole lines that readers accept.
// Concurrency: one writer thread per log.
#pragma once

#include <chrono>
#include <filesystem>
#include <string>
#include <string_view>

namespace flatslam {

class LineLog {
 public:
  enum class Mode { kTruncate, kAppend };
  // Opens the file; with kTruncate it starts empty and `header` (whole lines, may be empty) is
  // written at once. Throws flatslam::Error naming the file when it cannot be opened.
  LineLog(const std::filesystem::path& path, std::string_view header, Mode mode = Mode::kTruncate,
          std::chrono::milliseconds flush_interval = std::chrono::milliseconds(500));
  LineLog(const LineLog&) = delete;
  LineLog& operator=(const LineLog&) = delete;
  ~LineLog();  // flushes; errors are dropped (call Close to see them)

  // Appends text made of whole lines (ending in '\n'); flushes when the interval has passed.
  void Append(std::string_view lines);
  // Hands every buffered line to the OS now.
  void Flush();
  // Flushes and closes; throws flatslam::Error naming the file if any write failed.
  void Close();
  [[nodiscard]] const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
  int fd_ = -1;
  std::string buffer_;
  std::chrono::steady_clock::time_point last_flush_;
  std::chrono::milliseconds interval_;
  bool failed_ = false;
};

}  // namespace flatslam
