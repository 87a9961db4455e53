// Where tests find the real datasets and the flatslam executable.
#pragma once

#include <cstdlib>
#include <filesystem>
#include <string>

#include <unistd.h>

namespace flatslam::testing {

// Root of the shared real-data snippets (KITTI, EuRoC, reference trajectories).
inline std::filesystem::path DatasetsDir() {
  if (const char* env = std::getenv("FLATSLAM_DATASETS_DIR")) return env;
  return FLATSLAM_DATASETS_DIR;
}

inline std::string AppPath() { return FLATSLAM_APP_PATH; }

// A fresh empty directory under the system temp dir, removed by the caller if wanted.
inline std::filesystem::path FreshTempDir(const std::string& name) {
  auto dir = std::filesystem::temp_directory_path() / ("flatslam_test_" + name + "_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

}  // namespace flatslam::testing
