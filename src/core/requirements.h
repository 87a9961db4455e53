// The first broken requirement of an options struct, by the text of its condition, so that an
// error can say which field is wrong and why ("orb: min_fast_threshold <= fast_threshold").
// Concurrency: a value type; each check builds its own.
#pragma once

#include <string>
#include <string_view>

namespace flatslam {

class Requirements {
 public:
  // Records `text` unless an earlier requirement already failed.
  Requirements& Require(bool ok, std::string_view text) {
    if (!ok && first_.empty()) first_ = text;
    return *this;
  }
  // A nested struct's result, its text prefixed with the struct's name ("orb: ...").
  Requirements& Nested(std::string_view name, const std::string& problem) {
    if (!problem.empty() && first_.empty()) first_ = std::string(name) + ": " + problem;
    return *this;
  }
  // Empty when every requirement held.
  [[nodiscard]] const std::string& first() const { return first_; }

 private:
  std::string first_;
};

}  // namespace flatslam

// Requires `cond` of r, recording its source text when it fails.
#define FLATSLAM_REQUIRE(r, cond) (r).Require(static_cast<bool>(cond), #cond)
