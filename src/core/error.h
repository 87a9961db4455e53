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
  Error(const std::string& what, const char* where) : std::runtime_error(what), where_(where) {}
  // "file:line: condition" of the FLATSLAM_CHECK that failed (file relative to the source tree);
  // empty for errors raised otherwise. what() stays the message for the user.
  [[nodiscard]] const char* where() const { return where_; }

 private:
  const char* where_ = "";  // a string literal
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

namespace detail {
template <class... Args>
[[noreturn]] void FailCheck(const char* where, Args&&... args) {
  throw Error(Concat(std::forward<Args>(args)...), where);
}
}  // namespace detail

}  // namespace flatslam

#define FLATSLAM_DETAIL_STRING(x) #x
#define FLATSLAM_DETAIL_LINE(x) FLATSLAM_DETAIL_STRING(x)

// Checks a condition at an API or I/O boundary; on failure throws flatslam::Error with the
// streamed arguments as its message and "file:line: condition" as where().
#define FLATSLAM_CHECK(cond, ...)                                                                                    \
  do {                                                                                                               \
    if (!(cond)) ::flatslam::detail::FailCheck(__FILE__ ":" FLATSLAM_DETAIL_LINE(__LINE__) ": " #cond, __VA_ARGS__); \
  } while (false)
