#include "io/tum.h"

#include <cmath>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "io/dataset.h"
#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::ExpectErrorMentions;

// A tiny TUM RGB-D sequence written on the fly:
//   rgb   1.000 1.010 1.040 1.100
//   depth 1.004       1.045       1.300
// associate.py pairs (1.000, 1.004) [4 ms] and (1.040, 1.045) [5 ms]; 1.010 loses 1.004 to
// the closer 1.000; 1.100 and 1.300 have no partner within 20 ms.
class TumTiny : public ::testing::Test {
 protected:
  // fr3: the published calibration has no distortion, so pixels pass unchanged.
  void SetUp() override { dir_ = Make("rgbd_dataset_freiburg3_tiny"); }
  void TearDown() override { fs::remove_all(dir_.parent_path()); }

  static fs::path Make(const std::string& folder) {
    const fs::path dir = testing::FreshTempDir("tum_" + folder) / folder;
    fs::create_directories(dir / "rgb");
    fs::create_directories(dir / "depth");
    std::ofstream rgb(dir / "rgb.txt");
    rgb << "# color images\n# file: 'tiny.bag'\n# timestamp filename\n";
    for (const char* t : {"1.000000", "1.010000", "1.040000", "1.100000"}) {
      cv::Mat color(480, 640, CV_8UC3, cv::Scalar(10, 20, 30));
      EXPECT_TRUE(cv::imwrite((dir / "rgb" / (std::string(t) + ".png")).string(), color));
      rgb << t << " rgb/" << t << ".png\n";
    }
    std::ofstream depth(dir / "depth.txt");
    depth << "# depth maps\n# timestamp filename\n";
    for (const char* t : {"1.004000", "1.045000", "1.300000"}) {
      cv::Mat raw(480, 640, CV_16UC1, cv::Scalar(0));
      raw.at<uint16_t>(20, 10) = 5000;
      raw.at<uint16_t>(100, 200) = 12345;
      EXPECT_TRUE(cv::imwrite((dir / "depth" / (std::string(t) + ".png")).string(), raw));
      depth << t << " depth/" << t << ".png\n";
    }
    // Camera moves 0.6 m along x from t = 0.99 to t = 1.05, no rotation.
    std::ofstream(dir / "groundtruth.txt") << "# timestamp tx ty tz qx qy qz qw\n"
                                           << "0.9900 0 0 0 0 0 0 1\n"
                                           << "1.0500 0.6 0 0 0 0 0 1\n";
    return dir;
  }

  fs::path dir_;
};

TEST_F(TumTiny, AssociatesLikeAssociatePy) {
  const auto dataset = OpenDataset(dir_.string());
  ASSERT_EQ(dataset->size(), 2u);
  EXPECT_EQ(dataset->calibration().sensor, Sensor::kRgbd);
  const auto& tum = dynamic_cast<const TumDataset&>(*dataset);
  EXPECT_EQ(tum.unmatched_rgb(), 2u);
  EXPECT_EQ(dataset->read(0).t_ns, 1'000'000'000);
  EXPECT_EQ(tum.depth_t_ns(0), 1'004'000'000);
  EXPECT_EQ(dataset->read(1).t_ns, 1'040'000'000);
  EXPECT_EQ(tum.depth_t_ns(1), 1'045'000'000);
  EXPECT_NE(dataset->name().find("2 RGB frames without depth dropped"), std::string::npos) << dataset->name();
}

TEST_F(TumTiny, DepthInMetresAndGrayLeft) {
  const TumDataset dataset(dir_);
  const Frame frame = dataset.read(1);
  ASSERT_EQ(frame.left.type(), CV_8UC1);
  ASSERT_EQ(frame.depth.type(), CV_32FC1);
  EXPECT_EQ(frame.left.size(), cv::Size(640, 480));
  EXPECT_EQ(frame.depth.size(), cv::Size(640, 480));
  EXPECT_TRUE(frame.right.empty());
  EXPECT_NEAR(frame.left.at<uchar>(5, 5), 0.114 * 10 + 0.587 * 20 + 0.299 * 30, 1);
  EXPECT_FLOAT_EQ(frame.depth.at<float>(20, 10), 1.0f);
  EXPECT_FLOAT_EQ(frame.depth.at<float>(100, 200), 2.469f);
  EXPECT_EQ(frame.depth.at<float>(0, 0), 0.0f);
}

TEST_F(TumTiny, FreiburgIntrinsicsFromFolderName) {
  const TumDataset dataset(dir_);
  EXPECT_EQ(dataset.calibration_source(), "Freiburg intrinsics");
  const PinholeCamera& c = dataset.calibration().camera;
  EXPECT_DOUBLE_EQ(c.fx, 535.4);
  EXPECT_DOUBLE_EQ(c.fy, 539.2);
  EXPECT_DOUBLE_EQ(c.cx, 320.1);
  EXPECT_DOUBLE_EQ(c.cy, 247.6);
  EXPECT_EQ(c.width, 640);
  EXPECT_EQ(c.height, 480);
  EXPECT_DOUBLE_EQ(dataset.depth_factor(), 5000);
}

// fr1's colour camera is distorted (published k1 k2 p1 p2 k3 = 0.2624 -0.9531 -0.0054 0.0026
// 1.1633). A bright spot and a depth reading written where the raw camera sees the ray
// (0.4, 0.3, 1) come out where the undistorted camera the dataset reports projects that ray,
// colour and depth alike.
TEST(TumFreiburg1, ImagesAreUndistortedAndTheCameraIsTheUndistortedOne) {
  const fs::path dir = testing::FreshTempDir("tum_fr1") / "rgbd_dataset_freiburg1_desk";
  fs::create_directories(dir / "rgb");
  fs::create_directories(dir / "depth");
  const double fx = 517.3, fy = 516.5, cx = 318.6, cy = 255.3;
  const double k1 = 0.2624, k2 = -0.9531, p1 = -0.0054, p2 = 0.0026, k3 = 1.1633;
  const double x = 0.4, y = 0.3, r2 = x * x + y * y;
  const double radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
  const double xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x);
  const double yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y;
  const cv::Point raw(static_cast<int>(std::lround(fx * xd + cx)), static_cast<int>(std::lround(fy * yd + cy)));
  // Where the same ray lands without the distortion, to show the distortion matters here.
  const cv::Point2d pinhole(fx * x + cx, fy * y + cy);
  EXPECT_GT(cv::norm(cv::Point2d(raw) - pinhole), 5.0);
  cv::Mat color(480, 640, CV_8UC3, cv::Scalar(0, 0, 0));
  cv::circle(color, raw, 3, cv::Scalar(255, 255, 255), cv::FILLED);
  ASSERT_TRUE(cv::imwrite((dir / "rgb" / "1.000000.png").string(), color));
  cv::Mat depth(480, 640, CV_16UC1, cv::Scalar(0));
  cv::circle(depth, raw, 3, cv::Scalar(7500), cv::FILLED);
  ASSERT_TRUE(cv::imwrite((dir / "depth" / "1.000000.png").string(), depth));
  std::ofstream(dir / "rgb.txt") << "1.000000 rgb/1.000000.png\n";
  std::ofstream(dir / "depth.txt") << "1.000000 depth/1.000000.png\n";

  const TumDataset dataset(dir);
  EXPECT_EQ(dataset.calibration_source(), "Freiburg intrinsics and distortion");
  const PinholeCamera& c = dataset.calibration().camera;
  EXPECT_EQ(c.width, 640);
  EXPECT_EQ(c.height, 480);
  const cv::Point2d expected(c.fx * x + c.cx, c.fy * y + c.cy);
  const Frame frame = dataset.read(0);
  const cv::Moments spot = cv::moments(frame.left > 128, true);
  ASSERT_GT(spot.m00, 10);
  EXPECT_NEAR(spot.m10 / spot.m00, expected.x, 1.0);
  EXPECT_NEAR(spot.m01 / spot.m00, expected.y, 1.0);
  const cv::Moments reading = cv::moments(frame.depth > 0, true);
  ASSERT_GT(reading.m00, 10);
  EXPECT_NEAR(reading.m10 / reading.m00, expected.x, 1.0);
  EXPECT_NEAR(reading.m01 / reading.m00, expected.y, 1.0);
  double lowest = 0, highest = 0;
  cv::minMaxLoc(frame.depth, &lowest, &highest, nullptr, nullptr, frame.depth > 0);
  EXPECT_FLOAT_EQ(lowest, 1.5f);  // 7500 / 5000, never blended with the zeros around it
  EXPECT_FLOAT_EQ(highest, 1.5f);
  fs::remove_all(dir.parent_path());
}

TEST_F(TumTiny, GroundTruthIsInterpolatedAtFrames) {
  const TumDataset dataset(dir_);
  const auto gt = dataset.ground_truth();
  ASSERT_TRUE(gt.has_value());
  ASSERT_EQ(gt->size(), 2u);
  EXPECT_EQ((*gt)[0].t_ns, 1'000'000'000);
  EXPECT_NEAR((*gt)[0].T_world_cam.translation().x(), 0.1, 1e-12);
  EXPECT_NEAR((*gt)[1].T_world_cam.translation().x(), 0.5, 1e-12);
  EXPECT_TRUE((*gt)[1].T_world_cam.linear().isIdentity(1e-12));
}

TEST_F(TumTiny, MonoUsesEveryRgbFrame) {
  DatasetOptions mono;
  mono.sensor = Sensor::kMonocular;
  const auto dataset = OpenDataset(dir_.string(), mono);
  ASSERT_EQ(dataset->size(), 4u);
  EXPECT_TRUE(dataset->read(3).depth.empty());
  EXPECT_EQ(dataset->read(3).t_ns, 1'100'000'000);
  // 1.100 is 50 ms past the last ground-truth pose: left out; the other three are interpolated.
  ASSERT_TRUE(dataset->ground_truth().has_value());
  EXPECT_EQ(dataset->ground_truth()->size(), 3u);
}

TEST_F(TumTiny, StereoIsUnavailable) {
  DatasetOptions stereo;
  stereo.sensor = Sensor::kStereo;
  ExpectErrorMentions([&] { (void)OpenDataset(dir_.string(), stereo); }, {"stereo", "available: mono, rgbd"});
}

TEST_F(TumTiny, CameraTxtWins) {
  WriteTumCameraFile(dir_ / "camera.txt", {{500, 501, 320.5, 240.5, 640, 480}, 1000});
  const TumDataset dataset(dir_);
  EXPECT_EQ(dataset.calibration_source(), "camera.txt");
  EXPECT_DOUBLE_EQ(dataset.calibration().camera.fy, 501);
  EXPECT_DOUBLE_EQ(dataset.calibration().camera.cx, 320.5);
  EXPECT_FLOAT_EQ(dataset.read(0).depth.at<float>(20, 10), 5.0f);  // 5000 / 1000
}

TEST_F(TumTiny, MalformedCameraTxtNamesLine) {
  std::ofstream(dir_ / "camera.txt") << "# fx fy cx cy width height\n500 500 320 240 640\n";
  ExpectErrorMentions([&] { (void)TumDataset(dir_); }, {"camera.txt:2", "fx fy cx cy width height"});
  std::ofstream(dir_ / "camera.txt") << "500 500 320 240 640 abc\n";
  ExpectErrorMentions([&] { (void)TumDataset(dir_); }, {"camera.txt:1", "height", "abc"});
}

TEST_F(TumTiny, NoCalibrationNamesCameraTxt) {
  const fs::path other = dir_.parent_path() / "my_room";
  fs::rename(dir_, other);
  ExpectErrorMentions([&] { (void)TumDataset(other); }, {(other / "camera.txt").string(), "missing"});
  fs::rename(other, dir_);
}

TEST_F(TumTiny, WrongImageSizeNamesFile) {
  const auto path = dir_ / "rgb" / "1.040000.png";
  ASSERT_TRUE(cv::imwrite(path.string(), cv::Mat(240, 320, CV_8UC3, cv::Scalar(1, 2, 3))));
  const TumDataset dataset(dir_);
  ExpectErrorMentions([&] { (void)dataset.read(1); }, {path.string(), "320x240", "640x480"});
}

TEST_F(TumTiny, TruncatedDepthNamesFile) {
  const auto path = dir_ / "depth" / "1.004000.png";
  fs::resize_file(path, fs::file_size(path) / 2);
  const TumDataset dataset(dir_);
  ExpectErrorMentions([&] { (void)dataset.read(0); }, {path.string(), "truncated"});
}

TEST_F(TumTiny, EmptyOrMalformedListsNameTheFile) {
  std::ofstream(dir_ / "depth.txt") << "# nothing\n";
  ExpectErrorMentions([&] { (void)TumDataset(dir_); }, {"depth.txt", "no frames"});
  std::ofstream(dir_ / "rgb.txt") << "1.0\n";
  ExpectErrorMentions([&] { (void)TumDataset(dir_); }, {"rgb.txt:1", "timestamp filename"});
}

TEST(TumAssociation, EachStampUsedOnce) {
  const std::vector<int64_t> a = {0, 10, 40, 100}, b = {4, 45, 300};
  const auto pairs = io::AssociateStamps(a, b, 20);
  ASSERT_EQ(pairs.size(), 2u);
  EXPECT_EQ(pairs[0], std::make_pair(size_t{0}, size_t{0}));
  EXPECT_EQ(pairs[1], std::make_pair(size_t{2}, size_t{1}));
  EXPECT_TRUE(io::AssociateStamps(a, b, 4).empty());  // strict: |dt| < max
}

TEST(TumCameraFile, RoundTrips) {
  const auto dir = testing::FreshTempDir("tum_camera_file");
  const TumCameraFile written{{535.4, 539.2, 320.1, 247.6, 640, 480}, 5000};
  WriteTumCameraFile(dir / "camera.txt", written);
  const TumCameraFile read = ReadTumCameraFile(dir / "camera.txt");
  EXPECT_EQ(read.camera.fx, written.camera.fx);
  EXPECT_EQ(read.camera.cy, written.camera.cy);
  EXPECT_EQ(read.camera.width, 640);
  EXPECT_EQ(read.depth_factor, 5000);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace flatslam
