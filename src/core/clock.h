// Elapsed wall time, as the systems report their stages' times.
// Concurrency: pure functions over std::chrono::steady_clock.
#pragma once

#include <chrono>

namespace flatslam {

// Milliseconds of `d`.
[[nodiscard]] inline double Milliseconds(std::chrono::steady_clock::duration d) {
  return std::chrono::duration<double, std::milli>(d).count();
}

// Milliseconds since `start`.
[[nodiscard]] inline double MsSince(std::chrono::steady_clock::time_point start) {
  return Milliseconds(std::chrono::steady_clock::now() - start);
}

}  // namespace flatslam
