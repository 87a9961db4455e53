#include "io/image_folder.h"

#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "core/error.h"
#include "io/dataset.h"
#include "io/orb_settings.h"
#include "io/synthetic.h"
#include "expect_error.h"
#include "test_data.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::ExpectErrorMentions;

// A small room scene: 10 frames at 20 Hz, 320x240.
SyntheticScene SmallRoom(Sensor sensor) {
  SyntheticOptions o;
  o.width = 320;
  o.height = 240;
  o.frame_rate_hz = 20;
  o.duration_s = 0.5;
  o.sensor = sensor;
  return SyntheticScene(MakeScene("room"), o);
}

std::string FrameName(size_t i) {
  char name[32];
  std::snprintf(name, sizeof(name), "%06zu.png", i);
  return name;
}

// An ORB-SLAM2 settings file describing the scene's camera; `extra` is appended.
std::shared_ptr<const OrbSettings> SceneSettings(const SyntheticScene& scene, const fs::path& path,
                                                 const std::string& extra = "") {
  const Calibration& c = scene.calibration();
  std::ofstream out(path);
  char text[512];
  std::snprintf(text, sizeof(text),
                "%%YAML:1.0\nCamera.fx: %.17g\nCamera.fy: %.17g\nCamera.cx: %.17g\nCamera.cy: %.17g\n"
                "Camera.k1: 0.0\nCamera.k2: 0.0\nCamera.p1: 0.0\nCamera.p2: 0.0\n"
                "Camera.width: %d\nCamera.height: %d\nCamera.bf: %.17g\n",
                c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy, c.camera.width, c.camera.height,
                std::max(c.baseline_m, 0.1) * c.camera.fx);
  out << text << extra;
  out.close();
  return std::make_shared<const OrbSettings>(ReadOrbSettings(path));
}

std::unique_ptr<Dataset> Open(const fs::path& dir, std::shared_ptr<const OrbSettings> settings,
                              std::optional<Sensor> sensor = std::nullopt) {
  DatasetOptions options;
  options.settings = std::move(settings);
  options.sensor = sensor;
  return OpenDataset(dir.string(), options);
}

TEST(ImageFolder, StereoFolderGivesTheRenderedFrames) {
  const SyntheticScene scene = SmallRoom(Sensor::kStereo);
  const fs::path dir = testing::FreshTempDir("folder_stereo");
  fs::create_directories(dir / "left");
  fs::create_directories(dir / "right");
  std::vector<Frame> rendered;
  for (size_t i = 0; i < scene.frame_count(); ++i) {
    rendered.push_back(scene.Render(i));
    ASSERT_TRUE(cv::imwrite((dir / "left" / FrameName(i)).string(), rendered.back().left));
    ASSERT_TRUE(cv::imwrite((dir / "right" / FrameName(i)).string(), rendered.back().right));
  }
  WriteTum(dir / "groundtruth.txt", scene.GroundTruth());
  const auto settings = SceneSettings(scene, dir.parent_path() / "folder_stereo.yaml", "Camera.fps: 20.0\n");

  const auto dataset = Open(dir, settings);
  EXPECT_NE(dataset->name().find("images " + dir.filename().string() + " (stereo)"), std::string::npos)
      << dataset->name();
  ASSERT_EQ(dataset->size(), scene.frame_count());
  const Calibration& calib = dataset->calibration();
  const Calibration& truth = scene.calibration();
  EXPECT_EQ(calib.sensor, Sensor::kStereo);
  EXPECT_DOUBLE_EQ(calib.camera.fx, truth.camera.fx);
  EXPECT_DOUBLE_EQ(calib.camera.cy, truth.camera.cy);
  EXPECT_EQ(calib.camera.width, 320);
  EXPECT_EQ(calib.camera.height, 240);
  EXPECT_NEAR(calib.baseline_m, truth.baseline_m, 1e-12);
  EXPECT_EQ(calib.frame_rate_hz, 20);
  for (size_t i = 0; i < dataset->size(); ++i) {
    const Frame frame = dataset->read(i);
    EXPECT_EQ(frame.t_ns, scene.timestamp_ns(i));  // file names 000000, 000001 ... are frame numbers at 20 Hz
    EXPECT_EQ(cv::norm(frame.left, rendered[i].left, cv::NORM_INF), 0) << i;
    EXPECT_EQ(cv::norm(frame.right, rendered[i].right, cv::NORM_INF), 0) << i;
  }
  const auto gt = dataset->ground_truth();
  ASSERT_TRUE(gt.has_value());
  ASSERT_EQ(gt->size(), scene.frame_count());
  EXPECT_TRUE(gt->back().T_world_cam.isApprox(scene.GroundTruth().back().T_world_cam, 1e-9));

  // Monocular reads the left images; the KITTI-like image_0/ + image_1/ without calib.txt is a plain folder.
  EXPECT_EQ(Open(dir, settings, Sensor::kMonocular)->calibration().sensor, Sensor::kMonocular);
  fs::rename(dir / "left", dir / "image_0");
  fs::rename(dir / "right", dir / "image_1");
  EXPECT_EQ(DetectDatasetLayout(dir.string(), true), DatasetLayout::kImageFolder);
  EXPECT_EQ(Open(dir, settings)->size(), scene.frame_count());

  // Paired folders must hold as many images.
  fs::remove(dir / "image_1" / FrameName(3));
  ExpectErrorMentions([&] { (void)Open(dir, settings); }, {dir.string(), "image_0/ holds 10", "image_1/ holds 9"});
  ExpectErrorMentions([&] { (void)Open(dir, settings, Sensor::kRgbd); }, {"RGB-D requested", "rgb/ + depth/"});
}

TEST(ImageFolder, TimestampsFromNamesTimesTxtOrFrameRate) {
  const SyntheticScene scene = SmallRoom(Sensor::kMonocular);
  const fs::path dir = testing::FreshTempDir("folder_mono");
  const int64_t t0 = 1403636579763555584;  // EuRoC-style nanosecond names
  for (size_t i = 0; i < 4; ++i) {
    ASSERT_TRUE(cv::imwrite((dir / (std::to_string(t0 + 50'000'000 * static_cast<int64_t>(i)) + ".png")).string(),
                            scene.Render(i).left));
  }
  const fs::path settings_file = dir.parent_path() / "folder_mono.yaml";
  auto settings = SceneSettings(scene, settings_file);
  auto dataset = Open(dir, settings);
  EXPECT_EQ(dataset->calibration().sensor, Sensor::kMonocular);
  ASSERT_EQ(dataset->size(), 4u);
  EXPECT_EQ(dataset->read(0).t_ns, t0);
  EXPECT_EQ(dataset->read(3).t_ns, t0 + 150'000'000);
  EXPECT_NEAR(dataset->calibration().frame_rate_hz, 20, 1e-9);
  EXPECT_FALSE(dataset->ground_truth().has_value());

  // Names that are not numbers: times.txt, else the frame rate.
  for (size_t i = 0; i < 4; ++i) {
    fs::rename(dir / (std::to_string(t0 + 50'000'000 * static_cast<int64_t>(i)) + ".png"),
               dir / ("frame_" + std::to_string(i) + ".png"));
  }
  ExpectErrorMentions([&] { (void)Open(dir, settings); }, {dir.string(), "Camera.fps", "times.txt"});
  settings = SceneSettings(scene, settings_file, "Camera.fps: 25\n");
  EXPECT_EQ(Open(dir, settings)->read(2).t_ns, 80'000'000);
  std::ofstream(dir / "times.txt") << "0.0\n0.1\n0.25\n0.3\n";
  dataset = Open(dir, settings);
  EXPECT_EQ(dataset->read(2).t_ns, 250'000'000);
  EXPECT_EQ(dataset->read(2).left.size(), cv::Size(320, 240));
  std::ofstream(dir / "times.txt") << "0.0\n0.1\n0.2\n";
  ExpectErrorMentions([&] { (void)Open(dir, settings); }, {"times.txt", "lists 3 times", "holds 4 images"});
}

TEST(ImageFolder, RgbdFolderScalesDepthAndHonoursColourOrder) {
  const SyntheticScene scene = SmallRoom(Sensor::kRgbd);
  const fs::path dir = testing::FreshTempDir("folder_rgbd");
  fs::create_directories(dir / "rgb");
  fs::create_directories(dir / "depth");
  std::vector<cv::Mat> colour, depth;
  for (size_t i = 0; i < 3; ++i) {
    const Frame frame = scene.Render(i);
    // Channels that differ, so BGR and RGB weighting give different grey.
    cv::Mat inverted = 255 - frame.left, half = frame.left / 2;
    cv::Mat bgr;
    cv::merge(std::vector<cv::Mat>{frame.left, half, inverted}, bgr);
    colour.push_back(bgr);
    cv::Mat raw;
    frame.depth.convertTo(raw, CV_16U, 1000.0);  // millimetres
    depth.push_back(raw);
    ASSERT_TRUE(cv::imwrite((dir / "rgb" / FrameName(i)).string(), bgr));
    ASSERT_TRUE(cv::imwrite((dir / "depth" / FrameName(i)).string(), raw));
  }
  const auto settings = SceneSettings(scene, dir.parent_path() / "folder_rgbd.yaml",
                                      "Camera.fps: 20\nCamera.RGB: 1\nDepthMapFactor: 1000.0\n");
  const auto dataset = Open(dir, settings);
  EXPECT_EQ(dataset->calibration().sensor, Sensor::kRgbd);
  ASSERT_EQ(dataset->size(), 3u);
  const Frame frame = dataset->read(1);
  cv::Mat expected_gray, expected_depth;
  cv::cvtColor(colour[1], expected_gray, cv::COLOR_RGB2GRAY);  // Camera.RGB 1: channel 0 is red
  EXPECT_EQ(cv::norm(frame.left, expected_gray, cv::NORM_INF), 0);
  depth[1].convertTo(expected_depth, CV_32F, 1 / 1000.0);
  EXPECT_LT(cv::norm(frame.depth, expected_depth, cv::NORM_INF), 1e-6);
  EXPECT_GT(cv::countNonZero(frame.depth), 1000);
}

TEST(ImageFolder, WithoutSettingsTheErrorAsksForThem) {
  const SyntheticScene scene = SmallRoom(Sensor::kMonocular);
  const fs::path dir = testing::FreshTempDir("folder_nosettings");
  ASSERT_TRUE(cv::imwrite((dir / "a.png").string(), scene.Render(0).left));
  ExpectErrorMentions([&] { (void)OpenDataset(dir.string()); }, {dir.string(), "plain image folder", "settings file"});
  const fs::path empty = testing::FreshTempDir("folder_empty");
  const auto settings = SceneSettings(scene, empty.parent_path() / "folder_empty.yaml");
  ExpectErrorMentions([&] { (void)Open(empty, settings); }, {empty.string(), "holds no .png"});
  ExpectErrorMentions([&] { (void)OpenDataset(empty.string()); }, {"cannot tell the layout", "settings file"});
  // A size that does not match the settings names both.
  const fs::path small = testing::FreshTempDir("folder_small");
  cv::Mat tiny(100, 120, CV_8UC1, cv::Scalar(7));
  ASSERT_TRUE(cv::imwrite((small / "a.png").string(), tiny));
  ExpectErrorMentions([&] { (void)Open(small, settings)->read(0); }, {"a.png", "120x100", "320x240"});
}

}  // namespace
}  // namespace flatslam
