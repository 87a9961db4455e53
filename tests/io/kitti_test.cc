#include "io/kitti.h"

#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "io/dataset.h"
#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::ExpectErrorMentions;

fs::path Sequence(const std::string& nn) {
  return testing::DatasetsDir() / "kitti/sequences" / nn;
}

TEST(Kitti, Sequence07IsMonoWithGroundTruth) {
  const auto dataset = OpenDataset(Sequence("07").string());
  EXPECT_EQ(dataset->name(), "KITTI 07 (mono)");
  ASSERT_EQ(dataset->size(), 160u);
  const Calibration& calib = dataset->calibration();
  EXPECT_EQ(calib.sensor, Sensor::kMonocular);
  EXPECT_EQ(calib.camera.width, 1226);
  EXPECT_EQ(calib.camera.height, 370);
  EXPECT_DOUBLE_EQ(calib.camera.fx, 707.0912);
  EXPECT_DOUBLE_EQ(calib.camera.cy, 183.1104);
  EXPECT_NEAR(calib.frame_rate_hz, 10.0, 0.5);
  EXPECT_EQ(calib.baseline_m, 0.0);

  const Frame first = dataset->read(0);
  EXPECT_EQ(first.t_ns, 0);
  EXPECT_EQ(first.left.type(), CV_8UC1);
  EXPECT_EQ(first.left.size(), cv::Size(1226, 370));
  EXPECT_TRUE(first.right.empty());
  EXPECT_TRUE(first.depth.empty());
  const Frame last = dataset->read(159);
  EXPECT_EQ(last.index, 159u);
  EXPECT_GT(last.t_ns, 15'000'000'000);

  const auto gt = dataset->ground_truth();
  ASSERT_TRUE(gt.has_value());
  ASSERT_EQ(gt->size(), 160u);
  EXPECT_TRUE(gt->front().T_world_cam.isApprox(Eigen::Isometry3d::Identity(), 1e-9));
  EXPECT_EQ((*gt)[1].t_ns, 103'875'200);  // times.txt line 2: 1.038752e-01
  EXPECT_EQ(gt->back().t_ns, last.t_ns);
  // About 90 m driven over the snippet.
  double length = 0;
  for (size_t i = 1; i < gt->size(); ++i) {
    length += ((*gt)[i].T_world_cam.translation() - (*gt)[i - 1].T_world_cam.translation()).norm();
  }
  EXPECT_GT(length, 70);
  EXPECT_LT(length, 110);
}

TEST(Kitti, Sequence06IsStereoWithBaseline) {
  const auto dataset = OpenDataset(Sequence("06").string());
  EXPECT_EQ(dataset->name(), "KITTI 06 (stereo)");
  ASSERT_EQ(dataset->size(), 51u);
  EXPECT_EQ(dataset->calibration().sensor, Sensor::kStereo);
  EXPECT_NEAR(dataset->calibration().baseline_m, 0.537, 0.001);
  const Frame frame = dataset->read(50);
  EXPECT_EQ(frame.left.type(), CV_8UC1);
  EXPECT_EQ(frame.right.type(), CV_8UC1);
  EXPECT_EQ(frame.right.size(), frame.left.size());
  EXPECT_GT(cv::norm(frame.left, frame.right, cv::NORM_L1), 0);  // two different cameras
  ASSERT_TRUE(dataset->ground_truth().has_value());
  EXPECT_EQ(dataset->ground_truth()->size(), 51u);

  DatasetOptions mono;
  mono.sensor = Sensor::kMonocular;
  const auto left_only = OpenDataset(Sequence("06").string(), mono);
  EXPECT_EQ(left_only->calibration().sensor, Sensor::kMonocular);
  EXPECT_TRUE(left_only->read(0).right.empty());
}

TEST(Kitti, UnavailableSensorNamesWhatIsAvailable) {
  DatasetOptions stereo;
  stereo.sensor = Sensor::kStereo;
  ExpectErrorMentions([&] { (void)OpenDataset(Sequence("07").string(), stereo); }, {"image_1", "available: mono"});
  DatasetOptions rgbd;
  rgbd.sensor = Sensor::kRgbd;
  ExpectErrorMentions([&] { (void)OpenDataset(Sequence("06").string(), rgbd); }, {"RGB-D", "mono, stereo"});
}

TEST(Kitti, ReadIsThreadSafe) {
  const KittiDataset dataset(Sequence("06"));
  std::vector<double> sequential(8), parallel(8);
  for (size_t i = 0; i < 8; ++i) sequential[i] = cv::sum(dataset.read(i).right)[0];
  std::vector<std::thread> threads;
  for (size_t t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      for (size_t i = t; i < 8; i += 4) parallel[i] = cv::sum(dataset.read(i).right)[0];
    });
  }
  for (auto& thread : threads) thread.join();
  EXPECT_EQ(sequential, parallel);
  ExpectErrorMentions([&] { (void)dataset.read(51); }, {"51", "out of range"});
}

// A three-frame copy of sequence 07 in a temp dir, to break one file at a time.
class KittiBadInput : public ::testing::Test {
 protected:
  void SetUp() override {
    root_ = testing::FreshTempDir("kitti_bad");
    seq_ = root_ / "sequences" / "07";
    fs::create_directories(seq_ / "image_0");
    fs::create_directories(root_ / "poses");
    fs::copy_file(Sequence("07") / "calib.txt", seq_ / "calib.txt");
    std::ofstream(seq_ / "times.txt") << "0.000000e+00\n1.036000e-01\n2.072000e-01\n";
    for (int i = 0; i < 3; ++i) {
      const std::string name = "00000" + std::to_string(i) + ".png";
      fs::copy_file(Sequence("07") / "image_0" / name, seq_ / "image_0" / name);
    }
    std::ofstream poses(root_ / "poses" / "07.txt");
    for (int i = 0; i < 3; ++i) poses << "1 0 0 0 0 1 0 0 0 0 1 " << i << "\n";
  }
  void TearDown() override { fs::remove_all(root_); }

  fs::path root_, seq_;
};

TEST_F(KittiBadInput, CopyOpens) {
  const KittiDataset dataset(seq_);
  EXPECT_EQ(dataset.size(), 3u);
  EXPECT_EQ(dataset.read(2).t_ns, 207'200'000);
  ASSERT_TRUE(dataset.ground_truth().has_value());
  EXPECT_DOUBLE_EQ(dataset.ground_truth()->back().T_world_cam.translation().z(), 2.0);
}

TEST_F(KittiBadInput, MissingCalib) {
  fs::remove(seq_ / "calib.txt");
  ExpectErrorMentions([&] { (void)KittiDataset(seq_); }, {"calib.txt"});
}

TEST_F(KittiBadInput, MalformedCalibLineNamesLine) {
  std::ofstream(seq_ / "calib.txt") << "P0: 1 2 3 4 5 6 7 8 9 10 11\n";
  ExpectErrorMentions([&] { (void)KittiDataset(seq_); }, {"calib.txt:1", "12 numbers"});
}

TEST_F(KittiBadInput, EmptyTimes) {
  std::ofstream(seq_ / "times.txt").flush();
  ExpectErrorMentions([&] { (void)KittiDataset(seq_); }, {"times.txt", "no frames"});
}

TEST_F(KittiBadInput, MoreTimesThanImages) {
  std::ofstream(seq_ / "times.txt", std::ios::app) << "3.1e-01\n";
  ExpectErrorMentions([&] { (void)KittiDataset(seq_); }, {"000003.png", "times.txt"});
}

TEST_F(KittiBadInput, TruncatedPng) {
  const auto path = seq_ / "image_0" / "000001.png";
  const auto bytes = fs::file_size(path);
  fs::resize_file(path, bytes / 2);
  const KittiDataset dataset(seq_);
  ExpectErrorMentions([&] { (void)dataset.read(1); }, {"000001.png", "truncated"});
}

TEST_F(KittiBadInput, WrongImageSize) {
  ASSERT_TRUE(cv::imwrite((seq_ / "image_0" / "000002.png").string(), cv::Mat(50, 100, CV_8UC1, cv::Scalar(9))));
  const KittiDataset dataset(seq_);
  ExpectErrorMentions([&] { (void)dataset.read(2); }, {"000002.png", "100x50", "1226x370"});
}

TEST_F(KittiBadInput, PoseCountMismatch) {
  std::ofstream(root_ / "poses" / "07.txt") << "1 0 0 0 0 1 0 0 0 0 1 0\n";
  ExpectErrorMentions([&] { (void)KittiDataset(seq_); }, {"07.txt", "1 poses", "(3)"});
}

TEST(DatasetSpec, DetectsLayoutOrNamesWhatIsMissing) {
  ExpectErrorMentions([] { (void)OpenDataset("/nonexistent/flatslam/seq"); }, {"/nonexistent/flatslam/seq"});
  const auto dir = testing::FreshTempDir("dataset_spec_unknown");
  ExpectErrorMentions([&] { (void)OpenDataset(dir.string()); }, {dir.string(), "image_0", "mav0", "rgb.txt"});
  fs::remove_all(dir);
  EXPECT_EQ(OpenDataset((Sequence("07") / "").string())->name(), "KITTI 07 (mono)");  // trailing slash
  // synth: goes to the renderer, which names the unknown scene.
  ExpectErrorMentions([] { (void)OpenDataset("synth:no_such_scene"); }, {"no_such_scene"});
}

TEST(DatasetSpec, SensorNamesRoundTrip) {
  for (Sensor s : {Sensor::kMonocular, Sensor::kStereo, Sensor::kRgbd}) EXPECT_EQ(ParseSensor(SensorName(s)), s);
  EXPECT_EQ(ParseSensor("monocular"), Sensor::kMonocular);
  EXPECT_EQ(ParseSensor("RGBD"), Sensor::kRgbd);
  ExpectErrorMentions([] { (void)ParseSensor("lidar"); }, {"lidar", "mono, stereo or rgbd"});
}

}  // namespace
}  // namespace flatslam
