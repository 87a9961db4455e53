// Checked reading of the files dataset readers consume: images (gray, depth) and the small
// text files beside them (line lists, timestamps). Every failure is a flatslam::Error that
// names the file (and the line or the expected/actual size).
// Concurrency: stateless free functions, callable from any thread.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include <opencv2/core/mat.hpp>

namespace flatslam {

// Channel order of decoded colour images: OpenCV decodes to BGR; kRgb weighs the channels as R, G, B
// (ORB-SLAM's Camera.RGB: 1).
enum class ColorOrder { kBgr, kRgb };

// Reads an image as CV_8UC1. Color (3 or 4 channels, in `order`) is converted to gray; 16-bit
// intensity is scaled by 1/256. expected: required size, empty (0x0) = any size.
// Throws on a missing file, an undecodable (unreadable or truncated) file or a wrong size.
[[nodiscard]] cv::Mat ReadGrayImage(const std::filesystem::path& path, cv::Size expected = {},
                                    ColorOrder order = ColorOrder::kBgr);

// Reads a 16-bit single-channel depth image (TUM PNG) as CV_32FC1 metres: raw / depth_factor,
// raw 0 stays 0 (no measurement). TUM RGB-D uses depth_factor 5000.
[[nodiscard]] cv::Mat ReadDepthImage(const std::filesystem::path& path, double depth_factor, cv::Size expected = {});

// Size of an image file (decodes it once); throws like ReadGrayImage.
[[nodiscard]] cv::Size ReadImageSize(const std::filesystem::path& path);

// Text helpers shared by the readers; own namespace so they never clash with trajectory_io.
namespace io {

// One non-empty, non-comment line of a text file, trimmed, with its 1-based line number.
struct TextLine {
  int number = 0;
  std::string text;
};

// Reads the lines of a text file, dropping blank lines and lines starting with '#'
// (after leading whitespace). Throws naming the file when it is missing or unreadable.
[[nodiscard]] std::vector<TextLine> ReadTextLines(const std::filesystem::path& path);

// Splits on any of the separator characters, trimming blanks and dropping empty fields.
[[nodiscard]] std::vector<std::string> SplitFields(std::string_view text, std::string_view separators = " \t");

// An image file and its timestamp, as the list files of EuRoC (data.csv) and TUM RGB-D (rgb.txt,
// depth.txt) name them.
struct StampedFile {
  int64_t t_ns = 0;
  std::filesystem::path file;
};

// "WxH", as messages name an image size.
[[nodiscard]] std::string SizeText(cv::Size size);

// "file:line: " prefix of error messages.
[[nodiscard]] std::string Where(const std::filesystem::path& path, int line);

// Parses a double, throwing "file:line: expected a number for WHAT, got 'x'".
[[nodiscard]] double ParseNumber(const std::string& text, const std::filesystem::path& path, int line,
                                 std::string_view what);

// Parses seconds as written in TUM/KITTI files ("1305031102.175304", "1.044989e-01") into
// nanoseconds. Plain decimals are exact (no double rounding of 10-digit epochs); throws
// naming the file and line when it is not a number.
[[nodiscard]] int64_t ParseSecondsNs(const std::string& text, const std::filesystem::path& path, int line);

// Parses an integer nanosecond timestamp (EuRoC), throwing naming the file and line.
[[nodiscard]] int64_t ParseIntegerNs(const std::string& text, const std::filesystem::path& path, int line);

// Last component of a folder path, also for "." or a trailing slash ("seq/" -> "seq").
[[nodiscard]] std::string FolderName(const std::filesystem::path& dir);

// Nominal frame rate from the median interval of sorted timestamps; 0 with < 2 stamps.
[[nodiscard]] double MedianRateHz(const std::vector<int64_t>& t_ns);

}  // namespace io
}  // namespace flatslam
