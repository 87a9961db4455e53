#include "io/image_io.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <system_error>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"

namespace flatslam {
namespace {

// Distinguishes "missing" from "present but undecodable" so the message says which.
cv::Mat DecodeUnchanged(const std::filesystem::path& path) {
  std::error_code ec;
  FLATSLAM_CHECK(std::filesystem::is_regular_file(path, ec), "image not found: ", path.string());
  cv::Mat image = cv::imread(path.string(), cv::IMREAD_UNCHANGED);
  FLATSLAM_CHECK(!image.empty(), "cannot decode image (unreadable or truncated): ", path.string());
  return image;
}

void CheckSize(const cv::Mat& image, cv::Size expected, const std::filesystem::path& path) {
  if (expected.empty()) return;
  FLATSLAM_CHECK(image.size() == expected, "image ", path.string(), " is ", io::SizeText(image.size()), ", expected ",
                 io::SizeText(expected), " (from the calibration)");
}

}  // namespace

cv::Mat ReadGrayImage(const std::filesystem::path& path, cv::Size expected, ColorOrder order) {
  cv::Mat image = DecodeUnchanged(path);
  CheckSize(image, expected, path);
  if (image.depth() == CV_16U) image.convertTo(image, CV_8U, 1.0 / 256.0);
  FLATSLAM_CHECK(image.depth() == CV_8U, "image ", path.string(), " has an unsupported pixel type (",
                 cv::typeToString(image.type()), "), expected 8 or 16-bit");
  switch (image.channels()) {
    case 1:
      return image;
    case 3:
      cv::cvtColor(image, image, order == ColorOrder::kRgb ? cv::COLOR_RGB2GRAY : cv::COLOR_BGR2GRAY);
      return image;
    case 4:
      cv::cvtColor(image, image, order == ColorOrder::kRgb ? cv::COLOR_RGBA2GRAY : cv::COLOR_BGRA2GRAY);
      return image;
    default:
      Fail("image ", path.string(), " has ", image.channels(), " channels, expected 1, 3 or 4");
  }
}

cv::Mat ReadDepthImage(const std::filesystem::path& path, double depth_factor, cv::Size expected) {
  FLATSLAM_CHECK(depth_factor > 0, "depth factor must be positive (", depth_factor, ") for ", path.string());
  cv::Mat raw = DecodeUnchanged(path);
  CheckSize(raw, expected, path);
  FLATSLAM_CHECK(raw.type() == CV_16UC1, "depth image ", path.string(), " is ", cv::typeToString(raw.type()),
                 ", expected 16-bit single channel (CV_16UC1)");
  cv::Mat metres;
  raw.convertTo(metres, CV_32F, 1.0 / depth_factor);  // 0 maps to 0: no measurement
  return metres;
}

cv::Size ReadImageSize(const std::filesystem::path& path) {
  return DecodeUnchanged(path).size();
}

namespace io {

std::vector<TextLine> ReadTextLines(const std::filesystem::path& path) {
  std::error_code ec;
  FLATSLAM_CHECK(std::filesystem::is_regular_file(path, ec), "file not found: ", path.string());
  std::ifstream in(path);
  FLATSLAM_CHECK(in.good(), "cannot open ", path.string());
  std::vector<TextLine> lines;
  std::string line;
  int number = 0;
  while (std::getline(in, line)) {
    ++number;
    const auto first = line.find_first_not_of(" \t\r\n");
    if (first == std::string::npos || line[first] == '#') continue;
    const auto last = line.find_last_not_of(" \t\r\n");
    lines.push_back({number, line.substr(first, last - first + 1)});
  }
  FLATSLAM_CHECK(!in.bad(), "read error in ", path.string());
  return lines;
}

std::vector<std::string> SplitFields(std::string_view text, std::string_view separators) {
  std::vector<std::string> fields;
  size_t begin = 0;
  while (begin <= text.size()) {
    size_t end = text.find_first_of(separators, begin);
    if (end == std::string_view::npos) end = text.size();
    std::string_view field = text.substr(begin, end - begin);
    const auto first = field.find_first_not_of(" \t\r\n");
    if (first != std::string_view::npos) {
      const auto last = field.find_last_not_of(" \t\r\n");
      fields.emplace_back(field.substr(first, last - first + 1));
    }
    begin = end + 1;
  }
  return fields;
}

std::string SizeText(cv::Size size) {
  return std::to_string(size.width) + "x" + std::to_string(size.height);
}

std::string Where(const std::filesystem::path& path, int line) {
  return path.string() + ":" + std::to_string(line) + ": ";
}

double ParseNumber(const std::string& text, const std::filesystem::path& path, int line, std::string_view what) {
  char* end = nullptr;
  const double value = std::strtod(text.c_str(), &end);
  FLATSLAM_CHECK(!text.empty() && end == text.c_str() + text.size() && std::isfinite(value), Where(path, line),
                 "expected a number for ", what, ", got '", text, "'");
  return value;
}

int64_t ParseSecondsNs(const std::string& text, const std::filesystem::path& path, int line) {
  // Exact path: [-]digits[.digits], fraction rounded to 1 ns.
  size_t pos = 0;
  const bool negative = !text.empty() && text[0] == '-';
  if (negative || (!text.empty() && text[0] == '+')) pos = 1;
  const size_t int_begin = pos;
  while (pos < text.size() && std::isdigit(static_cast<unsigned char>(text[pos]))) ++pos;
  const size_t int_end = pos;
  size_t frac_begin = pos, frac_end = pos;
  if (pos < text.size() && text[pos] == '.') {
    frac_begin = ++pos;
    while (pos < text.size() && std::isdigit(static_cast<unsigned char>(text[pos]))) ++pos;
    frac_end = pos;
  }
  const bool plain = pos == text.size() && (int_end > int_begin || frac_end > frac_begin) && int_end - int_begin <= 10;
  if (plain) {
    int64_t seconds = 0;
    for (size_t i = int_begin; i < int_end; ++i) seconds = seconds * 10 + (text[i] - '0');
    int64_t fraction = 0;
    for (size_t i = 0; i < 9; ++i) {
      const size_t k = frac_begin + i;
      fraction = fraction * 10 + (k < frac_end ? text[k] - '0' : 0);
    }
    if (frac_end > frac_begin + 9 && text[frac_begin + 9] >= '5') ++fraction;
    const int64_t ns = seconds * 1'000'000'000 + fraction;
    return negative ? -ns : ns;
  }
  const double seconds = ParseNumber(text, path, line, "a time in seconds");
  FLATSLAM_CHECK(std::abs(seconds) < 9.2e9, Where(path, line), "time out of range: '", text, "'");
  return std::llround(seconds * 1e9);
}

int64_t ParseIntegerNs(const std::string& text, const std::filesystem::path& path, int line) {
  int64_t value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  FLATSLAM_CHECK(ec == std::errc() && end == text.data() + text.size(), Where(path, line),
                 "expected an integer timestamp in ns, got '", text, "'");
  return value;
}

std::string FolderName(const std::filesystem::path& dir) {
  std::filesystem::path normal = std::filesystem::absolute(dir).lexically_normal();
  if (!normal.has_filename()) normal = normal.parent_path();
  return normal.filename().string();
}

double MedianRateHz(const std::vector<int64_t>& t_ns) {
  if (t_ns.size() < 2) return 0;
  std::vector<int64_t> dt;
  dt.reserve(t_ns.size() - 1);
  for (size_t i = 1; i < t_ns.size(); ++i) dt.push_back(t_ns[i] - t_ns[i - 1]);
  std::nth_element(dt.begin(), dt.begin() + dt.size() / 2, dt.end());
  const int64_t median = dt[dt.size() / 2];
  return median > 0 ? 1e9 / static_cast<double>(median) : 0;
}

}  // namespace io
}  // namespace flatslam
