// Where tests find the real datasets and the flatslam executable.
#pragma once

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <system_error>
#include <vector>

#include <unistd.h>

namespace flatslam::testing {

// Root of the shared real-data snippets (KITTI, EuRoC, reference trajectories).
inline std::filesystem::path DatasetsDir() {
  if (const char* env = std::getenv("FLATSLAM_DATASETS_DIR")) return env;
  return FLATSLAM_DATASETS_DIR;
}

inline std::string AppPath() {
  return FLATSLAM_APP_PATH;
}

// A fresh empty directory under the system temp dir. It is removed when the test process exits
// normally, whether the test passed or failed (a crash leaves it for inspection).
inline std::filesystem::path FreshTempDir(const std::string& name) {
  static std::vector<std::filesystem::path> made;
  static const bool registered = std::atexit([] {
                                   for (const auto& d : made) {
                                     std::error_code ignored;
                                     std::filesystem::remove_all(d, ignored);
                                   }
                                 }) == 0;
  (void)registered;
  auto dir = std::filesystem::temp_directory_path() / ("flatslam_test_" + name + "_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  made.push_back(dir);
  return dir;
}

// Whole file as bytes (empty when it cannot be read).
inline std::string ReadBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

}  // namespace flatslam::testing
