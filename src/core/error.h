// Checked errors for API and I/O boundaries; the message names the file, line or field.
// Concurrency: stateless, callable from any thread.
#pragma once

#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>

namespace flatslam {

// Error raised on bad input or a violated API contract. Never used for numerical failure.
class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& what) : std::runtime_error(what) {}
};

namespace detail {
template <class... Args>
[[nodiscard]] std::string Concat(Args&&... args) {
  std::ostringstream out;
  (out << ... << std::forward<Args>(args));
  return out.str();
}
}  // namespace detail

// Throws flatslam::Error built from the streamed arguments.
template <class... Args>
[[noreturn]] void Fail(Args&&... args) {
  throw Error(detail::Concat(std::forward<Args>(args)...));
}

}  // namespace flatslam

// Checks a condition at an API or I/O boundary; on failure throws flatslam::Error.
#define FLATSLAM_CHECK(cond, ...)                                   \
  do {                                                              \
    if (!(cond)) ::flatslam::Fail(__VA_ARGS__);                     \
  } while (false)
