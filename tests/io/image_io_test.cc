#include "io/image_io.h"

#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

// Runs fn, expecting a flatslam::Error whose message holds every one of `parts`.
using testing::ExpectErrorMentions;

// Writes the first half of a valid PNG: a truncated download.
void WriteTruncatedPng(const fs::path& path, const cv::Mat& image) {
  std::vector<uchar> bytes;
  ASSERT_TRUE(cv::imencode(".png", image, bytes));
  std::ofstream out(path, std::ios::binary);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size() / 2));
}

cv::Mat Ramp(cv::Size size) {
  cv::Mat image(size, CV_8UC1);
  for (int y = 0; y < size.height; ++y)
    for (int x = 0; x < size.width; ++x) image.at<uchar>(y, x) = static_cast<uchar>((x * 7 + y * 3) % 256);
  return image;
}

TEST(ImageIo, ReadsKittiGrayImage) {
  const auto path = testing::DatasetsDir() / "kitti/sequences/07/image_0/000000.png";
  const cv::Mat image = ReadGrayImage(path, {1226, 370});
  EXPECT_EQ(image.type(), CV_8UC1);
  EXPECT_EQ(image.size(), cv::Size(1226, 370));
  EXPECT_EQ(ReadImageSize(path), cv::Size(1226, 370));
}

TEST(ImageIo, ConvertsColorAndSixteenBitToGray) {
  const auto dir = testing::FreshTempDir("image_io_gray");
  cv::Mat red(4, 6, CV_8UC3, cv::Scalar(0, 0, 255));  // BGR
  ASSERT_TRUE(cv::imwrite((dir / "red.png").string(), red));
  const cv::Mat gray = ReadGrayImage(dir / "red.png");
  ASSERT_EQ(gray.type(), CV_8UC1);
  EXPECT_NEAR(gray.at<uchar>(2, 3), 76, 1);  // 0.299 * 255

  cv::Mat wide(4, 6, CV_16UC1, cv::Scalar(200 * 256));
  ASSERT_TRUE(cv::imwrite((dir / "wide.png").string(), wide));
  const cv::Mat scaled = ReadGrayImage(dir / "wide.png");
  ASSERT_EQ(scaled.type(), CV_8UC1);
  EXPECT_EQ(scaled.at<uchar>(1, 1), 200);
  fs::remove_all(dir);
}

TEST(ImageIo, MissingFileIsNamed) {
  const auto dir = testing::FreshTempDir("image_io_missing");
  const auto path = dir / "nothere.png";
  ExpectErrorMentions([&] { (void)ReadGrayImage(path); }, {"not found", path.string()});
  fs::remove_all(dir);
}

TEST(ImageIo, TruncatedPngIsNamed) {
  const auto dir = testing::FreshTempDir("image_io_truncated");
  const auto path = dir / "half.png";
  WriteTruncatedPng(path, Ramp({320, 240}));
  ExpectErrorMentions([&] { (void)ReadGrayImage(path); }, {"truncated", path.string()});
  ExpectErrorMentions([&] { (void)ReadDepthImage(path, 5000); }, {"truncated", path.string()});
  fs::remove_all(dir);
}

TEST(ImageIo, GarbageFileIsNamed) {
  const auto dir = testing::FreshTempDir("image_io_garbage");
  const auto path = dir / "text.png";
  std::ofstream(path) << "not an image\n";
  ExpectErrorMentions([&] { (void)ReadGrayImage(path); }, {"cannot decode", path.string()});
  fs::remove_all(dir);
}

TEST(ImageIo, WrongSizeNamesFileAndBothSizes) {
  const auto dir = testing::FreshTempDir("image_io_size");
  const auto path = dir / "small.png";
  ASSERT_TRUE(cv::imwrite(path.string(), Ramp({100, 50})));
  ExpectErrorMentions([&] { (void)ReadGrayImage(path, {1226, 370}); }, {path.string(), "100x50", "1226x370"});
  EXPECT_NO_THROW((void)ReadGrayImage(path, {100, 50}));
  fs::remove_all(dir);
}

TEST(ImageIo, DepthPngBecomesMetres) {
  const auto dir = testing::FreshTempDir("image_io_depth");
  cv::Mat raw(3, 4, CV_16UC1, cv::Scalar(0));
  raw.at<uint16_t>(1, 2) = 5000;
  raw.at<uint16_t>(2, 3) = 12345;
  ASSERT_TRUE(cv::imwrite((dir / "depth.png").string(), raw));
  const cv::Mat depth = ReadDepthImage(dir / "depth.png", 5000, {4, 3});
  ASSERT_EQ(depth.type(), CV_32FC1);
  EXPECT_FLOAT_EQ(depth.at<float>(1, 2), 1.0f);
  EXPECT_FLOAT_EQ(depth.at<float>(2, 3), 2.469f);
  EXPECT_EQ(depth.at<float>(0, 0), 0.0f);  // no measurement stays 0

  ASSERT_TRUE(cv::imwrite((dir / "eight.png").string(), Ramp({4, 3})));
  ExpectErrorMentions([&] { (void)ReadDepthImage(dir / "eight.png", 5000); }, {"eight.png", "16-bit"});
  ExpectErrorMentions([&] { (void)ReadDepthImage(dir / "depth.png", 0); }, {"depth factor"});
  fs::remove_all(dir);
}

TEST(TextIo, SecondsParseExactly) {
  const fs::path file = "times.txt";
  EXPECT_EQ(io::ParseSecondsNs("1305031102.175304", file, 1), 1305031102175304000);
  EXPECT_EQ(io::ParseSecondsNs("1403715273.26214", file, 1), 1403715273262140000);
  EXPECT_EQ(io::ParseSecondsNs("0.1044989", file, 1), 104498900);
  EXPECT_EQ(io::ParseSecondsNs("1.044989e-01", file, 1), 104498900);
  EXPECT_EQ(io::ParseSecondsNs("-0.5", file, 1), -500000000);
  EXPECT_EQ(io::ParseSecondsNs("2.0000000006", file, 1), 2000000001);  // rounds below 1 ns
  ExpectErrorMentions([&] { (void)io::ParseSecondsNs("abc", file, 7); }, {"times.txt:7", "abc"});
  EXPECT_EQ(io::ParseIntegerNs("1403715273262142976", file, 1), 1403715273262142976);
  ExpectErrorMentions([&] { (void)io::ParseIntegerNs("14037.5", file, 3); }, {"times.txt:3"});
}

TEST(TextIo, LinesSkipCommentsAndBlanks) {
  const auto dir = testing::FreshTempDir("text_io_lines");
  std::ofstream(dir / "a.txt") << "# header\n\n  1 2 3 \r\n   # indented comment\nfour\n";
  const auto lines = io::ReadTextLines(dir / "a.txt");
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_EQ(lines[0].number, 3);
  EXPECT_EQ(lines[0].text, "1 2 3");
  EXPECT_EQ(lines[1].number, 5);
  EXPECT_EQ(io::SplitFields(" a, b ,,c ", ","), (std::vector<std::string>{"a", "b", "c"}));
  ExpectErrorMentions([&] { (void)io::ReadTextLines(dir / "b.txt"); }, {"b.txt"});
  EXPECT_EQ(io::FolderName(dir / "seq" / ""), "seq");
  EXPECT_NEAR(io::MedianRateHz({0, 50'000'000, 100'000'000, 400'000'000}), 20.0, 1e-9);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace flatslam
