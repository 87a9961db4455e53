// Small text helpers shared by the dataset readers, the option parser and the reports.
// Concurrency: pure functions.
#pragma once

#include <cstdio>
#include <string>
#include <string_view>

namespace flatslam {

// `text` without its leading and trailing blanks (space, tab, CR, LF, vertical tab, form feed).
// The view points into `text`: keep what it views alive while the view is used.
[[nodiscard]] inline std::string_view TrimBlanks(std::string_view text) {
  constexpr std::string_view kBlanks = " \t\r\n\v\f";
  const size_t begin = text.find_first_not_of(kBlanks);
  if (begin == std::string_view::npos) return {};
  return text.substr(begin, text.find_last_not_of(kBlanks) - begin + 1);
}

// The same, as a string of its own.
[[nodiscard]] inline std::string Trimmed(std::string_view text) {
  return std::string(TrimBlanks(text));
}

// `value` with `decimals` digits after the point, as printf's "%.*f" writes it.
[[nodiscard]] inline std::string FixedDecimals(double value, int decimals) {
  char text[64];
  std::snprintf(text, sizeof(text), "%.*f", decimals, value);
  return text;
}

}  // namespace flatslam
