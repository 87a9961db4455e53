#include "io/orb_settings.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "core/error.h"
#include "io/dataset.h"
#include "io/dataset_writer.h"
#include "io/euroc.h"
#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::ExpectErrorMentions;

fs::path WriteFile(const std::string& name, const std::string& text) {
  static const fs::path dir = testing::FreshTempDir("orb_settings");
  const fs::path path = dir / name;
  std::ofstream(path) << text;
  return path;
}

// A settings file's text with lines appended.
std::string Appended(const char* text, const char* lines) {
  std::string out = text;
  out.append(lines);
  return out;
}

std::string Option(const OrbSettings& settings, const std::string& key) {
  for (const auto& [k, v] : settings.slam_options)
    if (k == key) return v;
  return "(unset)";
}

fs::path Euroc() {
  return testing::DatasetsDir() / "euroc/V1_01_first20";
}

// ORB-SLAM2's monocular file for TUM fr1 (distorted Kinect camera, no size: taken from the images).
const char* const kOrbSlam2Mono = R"(%YAML:1.0

# Camera Parameters. Adjust them!
Camera.fx: 517.306408
Camera.fy: 516.469215
Camera.cx: 318.643040
Camera.cy: 255.313989

Camera.k1: 0.262383
Camera.k2: -0.953104
Camera.p1: -0.005358
Camera.p2: 0.002628
Camera.k3: 1.163314

# Camera frames per second
Camera.fps: 30.0

# Color order of the images (0: BGR, 1: RGB. It is ignored if images are grayscale)
Camera.RGB: 1

ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7

Viewer.KeyFrameSize: 0.05
Viewer.KeyFrameLineWidth: 1
Viewer.PointSize: 2
Viewer.ViewpointX: 0
Viewer.ViewpointY: -0.7
Viewer.ViewpointF: 500
)";

const char* const kOrbSlam2KittiStereo = R"(%YAML:1.0
Camera.fx: 718.856
Camera.fy: 718.856
Camera.cx: 607.1928
Camera.cy: 185.2157

Camera.k1: 0.0
Camera.k2: 0.0
Camera.p1: 0.0
Camera.p2: 0.0

Camera.width: 1241
Camera.height: 376

Camera.fps: 10.0

# stereo baseline times fx
Camera.bf: 386.1448

Camera.RGB: 1

# Close/Far threshold. Baseline times.
ThDepth: 35

ORBextractor.nFeatures: 2000
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
)";

const char* const kOrbSlam2Rgbd = R"(%YAML:1.0
Camera.fx: 517.306408
Camera.fy: 516.469215
Camera.cx: 318.643040
Camera.cy: 255.313989
Camera.k1: 0.262383
Camera.k2: -0.953104
Camera.p1: -0.005358
Camera.p2: 0.002628
Camera.k3: 1.163314
Camera.width: 640
Camera.height: 480
Camera.fps: 30.0
# IR projector baseline times fx (aprox.)
Camera.bf: 40.0
Camera.RGB: 1
ThDepth: 40.0
# Deptmap values factor
DepthMapFactor: 5000.0
ORBextractor.nFeatures: 1000
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
)";

// ORB-SLAM2 stereo for EuRoC: the camera is the rectified one (LEFT.P), the raw cameras and the
// rectification are in the LEFT/RIGHT blocks.
const char* const kOrbSlam2EurocStereo = R"(%YAML:1.0
Camera.fx: 435.2046959714599
Camera.fy: 435.2046959714599
Camera.cx: 367.4517211914062
Camera.cy: 252.2008514404297
Camera.k1: 0.0
Camera.k2: 0.0
Camera.p1: 0.0
Camera.p2: 0.0
Camera.width: 752
Camera.height: 480
Camera.fps: 20.0
Camera.bf: 47.90639384423901
Camera.RGB: 1
ThDepth: 35

LEFT.height: 480
LEFT.width: 752
LEFT.D: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data:[-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0]
LEFT.K: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [458.654, 0.0, 367.215, 0.0, 457.296, 248.375, 0.0, 0.0, 1.0]
LEFT.R:  !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [0.99995000041666, 0.0, 0.0099998333341667, 0.0, 1.0, 0.0, -0.0099998333341667, 0.0, 0.99995000041666]
LEFT.P:  !!opencv-matrix
   rows: 3
   cols: 4
   dt: d
   data: [435.2046959714599, 0, 367.4517211914062, 0,  0, 435.2046959714599, 252.2008514404297, 0,  0, 0, 1, 0]

RIGHT.height: 480
RIGHT.width: 752
RIGHT.D: !!opencv-matrix
   rows: 1
   cols: 4
   dt: d
   data:[-0.28368365, 0.07451284, -0.00010473, -3.555907e-05]
RIGHT.K: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [457.587, 0.0, 379.999, 0.0, 456.134, 255.238, 0.0, 0.0, 1]
RIGHT.R:  !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [0.99995000041666, 0.0, -0.0099998333341667, 0.0, 1.0, 0.0, 0.0099998333341667, 0.0, 0.99995000041666]
RIGHT.P:  !!opencv-matrix
   rows: 3
   cols: 4
   dt: d
   data: [435.2046959714599, 0, 367.4517211914062, -47.90639384423901,
          0, 435.2046959714599, 252.2008514404297, 0, 0, 0, 1, 0]

ORBextractor.nFeatures: 1200
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7
)";

// ORB-SLAM3 (File.version 1.0) PinHole stereo for EuRoC: two raw cameras and the pose of camera 2 in
// camera 1 (from the sequence's T_BS), rectified by the reader; IMU and viewer keys are ignored.
const char* const kOrbSlam3EurocStereo = R"(%YAML:1.0
File.version: "1.0"
Camera.type: "PinHole"

Camera1.fx: 458.654
Camera1.fy: 457.296
Camera1.cx: 367.215
Camera1.cy: 248.375
Camera1.k1: -0.28340811
Camera1.k2: 0.07395907
Camera1.p1: 0.00019359
Camera1.p2: 1.76187114e-05

Camera2.fx: 457.587
Camera2.fy: 456.134
Camera2.cx: 379.999
Camera2.cy: 255.238
Camera2.k1: -0.28368365
Camera2.k2: 0.07451284
Camera2.p1: -0.00010473
Camera2.p2: -3.55590700e-05

Camera.width: 752
Camera.height: 480
Camera.fps: 20
Camera.RGB: 1

Stereo.ThDepth: 60.0
Stereo.T_c1_c2: !!opencv-matrix
  rows: 4
  cols: 4
  dt: f
  data: [0.999997256, -0.002317136, -0.000343393, 0.110074138,
         0.002312067, 0.999898049, -0.014090668, -0.000156612,
         0.000376008, 0.014089836, 0.999900663, 0.000889383,
         0, 0, 0, 1.000000000]

IMU.NoiseGyro: 1.7e-4
IMU.NoiseAcc: 2.0000e-3
IMU.GyroWalk: 1.9393e-05
IMU.AccWalk: 3.0000e-03
IMU.Frequency: 200.0
IMU.T_b_c1: !!opencv-matrix
  rows: 4
  cols: 4
  dt: f
  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]

ORBextractor.nFeatures: 1200
ORBextractor.scaleFactor: 1.2
ORBextractor.nLevels: 8
ORBextractor.iniThFAST: 20
ORBextractor.minThFAST: 7

Viewer.KeyFrameSize: 0.05
Viewer.imageViewScale: 1.0
System.thFarPoints: 20.0
)";

TEST(OrbSettings, OrbSlam2Monocular) {
  const OrbSettings s = ReadOrbSettings(WriteFile("mono.yaml", kOrbSlam2Mono));
  EXPECT_EQ(s.orb_slam_version, 2);
  EXPECT_DOUBLE_EQ(s.camera.fx, 517.306408);
  EXPECT_DOUBLE_EQ(s.camera.fy, 516.469215);
  EXPECT_DOUBLE_EQ(s.camera.cx, 318.643040);
  EXPECT_DOUBLE_EQ(s.camera.cy, 255.313989);
  EXPECT_EQ(s.camera.distortion, (std::array<double, 5>{0.262383, -0.953104, -0.005358, 0.002628, 1.163314}));
  EXPECT_TRUE(s.camera.distorted());
  EXPECT_TRUE(s.size.empty());  // from the images
  EXPECT_EQ(s.baseline_m, 0);
  EXPECT_EQ(s.frame_rate_hz, 30);
  EXPECT_TRUE(s.rgb);
  EXPECT_EQ(s.depth_map_factor, 0);
  EXPECT_FALSE(s.left_block || s.right_camera || s.T_left_right);
  EXPECT_EQ(Option(s, "orb.features"), "1000");
  EXPECT_EQ(Option(s, "orb.scale_factor"), "1.2");
  EXPECT_EQ(Option(s, "orb.levels"), "8");
  EXPECT_EQ(Option(s, "orb.fast_threshold"), "20");
  EXPECT_EQ(Option(s, "orb.min_fast_threshold"), "7");
  EXPECT_EQ(Option(s, "close_depth_baselines"), "(unset)");
}

TEST(OrbSettings, OrbSlam2KittiStereo) {
  const OrbSettings s = ReadOrbSettings(WriteFile("kitti.yaml", kOrbSlam2KittiStereo));
  EXPECT_DOUBLE_EQ(s.camera.fx, 718.856);
  EXPECT_DOUBLE_EQ(s.camera.cy, 185.2157);
  EXPECT_FALSE(s.camera.distorted());
  EXPECT_EQ(s.size, cv::Size(1241, 376));
  EXPECT_DOUBLE_EQ(s.baseline_m, 386.1448 / 718.856);
  EXPECT_EQ(s.frame_rate_hz, 10);
  EXPECT_EQ(Option(s, "orb.features"), "2000");
  EXPECT_EQ(Option(s, "close_depth_baselines"), "35");
  // Stereo: the baseline stays in the calibration, not in the options.
  const auto stereo = SettingsSlamOptions(s, Sensor::kStereo);
  EXPECT_TRUE(
      std::none_of(stereo.begin(), stereo.end(), [](const auto& kv) { return kv.first == "rgbd_virtual_baseline_m"; }));
}

TEST(OrbSettings, OrbSlam2Rgbd) {
  const OrbSettings s = ReadOrbSettings(WriteFile("rgbd.yaml", kOrbSlam2Rgbd));
  EXPECT_EQ(s.depth_map_factor, 5000);
  EXPECT_EQ(s.size, cv::Size(640, 480));
  EXPECT_EQ(Option(s, "close_depth_baselines"), "40");
  // Camera.bf of an RGB-D file is the virtual stereo baseline times fx.
  const auto options = SettingsSlamOptions(s, Sensor::kRgbd);
  const auto it = std::find_if(options.begin(), options.end(),
                               [](const auto& kv) { return kv.first == "rgbd_virtual_baseline_m"; });
  ASSERT_NE(it, options.end());
  EXPECT_NEAR(std::stod(it->second), 40.0 / 517.306408, 1e-12);
}

TEST(OrbSettings, OrbSlam2EurocStereoWithRectificationBlocks) {
  const OrbSettings s = ReadOrbSettings(WriteFile("euroc2.yaml", kOrbSlam2EurocStereo));
  ASSERT_TRUE(s.left_block && s.right_block);
  EXPECT_DOUBLE_EQ(s.camera.fx, 435.2046959714599);  // the rectified camera, LEFT.P
  EXPECT_FALSE(s.camera.distorted());
  EXPECT_DOUBLE_EQ(s.left_block->K(0, 0), 458.654);
  EXPECT_DOUBLE_EQ(s.left_block->K(1, 2), 248.375);
  EXPECT_EQ(s.left_block->D.cols, 5);
  EXPECT_EQ(s.right_block->D.cols, 4);
  EXPECT_DOUBLE_EQ(s.right_block->D.at<double>(0, 0), -0.28368365);
  EXPECT_DOUBLE_EQ(s.left_block->R(0, 2), 0.0099998333341667);
  EXPECT_DOUBLE_EQ(s.right_block->P(0, 3), -47.90639384423901);
  EXPECT_EQ(s.size, cv::Size(752, 480));
  EXPECT_NEAR(s.baseline_m, 47.90639384423901 / 435.2046959714599, 1e-12);
  // The stored images are taken with the raw left camera.
  EXPECT_DOUBLE_EQ(s.raw_camera().fx, 458.654);
  EXPECT_EQ(s.raw_camera().width, 752);
  EXPECT_EQ(Option(s, "orb.features"), "1200");
}

TEST(OrbSettings, OrbSlam3PinHoleStereo) {
  const OrbSettings s = ReadOrbSettings(WriteFile("euroc3.yaml", kOrbSlam3EurocStereo));
  EXPECT_EQ(s.orb_slam_version, 3);
  EXPECT_DOUBLE_EQ(s.camera.fx, 458.654);
  EXPECT_DOUBLE_EQ(s.camera.distortion[0], -0.28340811);
  EXPECT_EQ(s.camera.distortion[4], 0);
  ASSERT_TRUE(s.right_camera && s.T_left_right);
  EXPECT_DOUBLE_EQ(s.right_camera->cx, 379.999);
  EXPECT_DOUBLE_EQ(s.right_camera->distortion[3], -3.55590700e-05);
  EXPECT_NEAR(s.T_left_right->translation().x(), 0.110074138, 1e-7);
  EXPECT_NEAR(s.baseline_m, 0.110077842, 1e-6);
  EXPECT_EQ(s.frame_rate_hz, 20);
  EXPECT_EQ(Option(s, "close_depth_baselines"), "60");
  EXPECT_EQ(Option(s, "orb.features"), "1200");
}

TEST(OrbSettings, OrbSlam3RectifiedStereo) {
  const OrbSettings s = ReadOrbSettings(WriteFile("rectified3.yaml", R"(%YAML:1.0
File.version: "1.0"
Camera.type: "Rectified"
Camera1.fx: 718.856
Camera1.fy: 718.856
Camera1.cx: 607.1928
Camera1.cy: 185.2157
Stereo.b: 0.53716
Camera.width: 1241
Camera.height: 376
Camera.newWidth: 1241
Camera.newHeight: 376
Stereo.ThDepth: 40.0
)"));
  EXPECT_DOUBLE_EQ(s.baseline_m, 0.53716);
  EXPECT_EQ(Option(s, "close_depth_baselines"), "40");
}

TEST(OrbSettings, UnknownKeyIsNamedWithTheFile) {
  const fs::path path =
      WriteFile("unknown.yaml", Appended(kOrbSlam2KittiStereo, "Camera.fxx: 1\nLoopClosing.on: 1\n"));
  ExpectErrorMentions([&] { (void)ReadOrbSettings(path); },
                      {path.string(), "unknown keys", "'Camera.fxx'", "'LoopClosing.on'"});
}

TEST(OrbSettings, ContradictoryKeysAreNamed) {
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("fx.yaml", Appended(kOrbSlam2KittiStereo, "Camera1.fx: 700.0\n"))); },
      {"'Camera.fx'", "'Camera1.fx'", "718.856", "700", "disagree"});
  // The same value under both names is fine.
  EXPECT_NO_THROW(
      (void)ReadOrbSettings(WriteFile("fx_same.yaml", Appended(kOrbSlam2KittiStereo, "Camera1.fx: 718.856\n"))));
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("bf.yaml", Appended(kOrbSlam2KittiStereo, "Stereo.b: 0.12\n"))); },
      {"'Camera.bf / fx'", "'Stereo.b'", "disagree"});
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("th.yaml", Appended(kOrbSlam2KittiStereo, "Stereo.ThDepth: 40\n"))); },
      {"'ThDepth'", "'Stereo.ThDepth'"});
  std::string left_p = kOrbSlam2EurocStereo;
  left_p.replace(left_p.find("Camera.cx: 367.4517211914062"), 28, "Camera.cx: 360.0");
  ExpectErrorMentions([&] { (void)ReadOrbSettings(WriteFile("leftp.yaml", left_p)); }, {"'Camera.cx'", "'LEFT.P'"});
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("dup.yaml", Appended(kOrbSlam2KittiStereo, "ThDepth: 35\n"))); },
      {"'ThDepth'", "twice"});
}

TEST(OrbSettings, MissingAndNonPositiveFocalLengthAreNamed) {
  std::string missing = kOrbSlam2Mono;
  missing.erase(missing.find("Camera.fx: 517.306408"), 21);
  const fs::path path = WriteFile("missing.yaml", missing);
  ExpectErrorMentions([&] { (void)ReadOrbSettings(path); }, {path.string(), "missing key 'Camera.fx'", "Camera1.fx"});
  std::string negative = kOrbSlam2Mono;
  negative.replace(negative.find("Camera.fy: 516.469215"), 21, "Camera.fy: -516.4");
  ExpectErrorMentions([&] { (void)ReadOrbSettings(WriteFile("negative.yaml", negative)); },
                      {"'Camera.fy'", "positive"});
}

TEST(OrbSettings, FisheyeResizeAndMalformedFilesAreRejected) {
  ExpectErrorMentions(
      [] {
        (void)ReadOrbSettings(WriteFile("kb8.yaml", R"(%YAML:1.0
File.version: "1.0"
Camera.type: "KannalaBrandt8"
Camera1.fx: 190.97
Camera1.fy: 190.97
Camera1.cx: 254.93
Camera1.cy: 256.89
Camera1.k1: 0.0034
Camera1.k2: 0.0007
Camera1.k3: -0.0020
Camera1.k4: 0.0002
Camera1.overlappingBegin: 0
)"));
      },
      {"KannalaBrandt8", "fisheye", "not supported"});
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("k4.yaml", Appended(kOrbSlam2Mono, "Camera.k4: 0.1\n"))); },
      {"'Camera.k4'", "fisheye"});
  ExpectErrorMentions(
      [] {
        (void)ReadOrbSettings(WriteFile(
            "resize.yaml", Appended(kOrbSlam2KittiStereo, "Camera.newWidth: 600\nCamera.newHeight: 188\n")));
      },
      {"'Camera.newWidth'", "600x188", "resizing is not supported"});
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("scale.yaml", Appended(kOrbSlam2Mono, "Camera.imageScale: 0.5\n"))); },
      {"'Camera.imageScale'", "resiz"});
  EXPECT_NO_THROW((void)ReadOrbSettings(
      WriteFile("scale1.yaml", Appended(kOrbSlam2Mono, "Camera.imageScale: 1\nCamera.bFishEye: 0\n"))));
  ExpectErrorMentions([] { (void)ReadOrbSettings(WriteFile("header.yaml", "Camera.fx: 500\n")); }, {"%YAML:1.0"});
  ExpectErrorMentions([] { (void)ReadOrbSettings("/nonexistent/settings.yaml"); },
                      {"not found", "/nonexistent/settings.yaml"});
  ExpectErrorMentions([] { (void)ReadOrbSettings(WriteFile("broken.yaml", "%YAML:1.0\nCamera.fx: [1\n")); },
                      {"broken.yaml"});
  // A tab after a value (YAML allows none outside comments) is named with its line.
  ExpectErrorMentions(
      [] {
        (void)ReadOrbSettings(
            WriteFile("tab.yaml", "%YAML:1.0\n# a comment with a tab\t\nCamera.fx: 500.0\nCamera.fy: 500.0\t\n"));
      },
      {"tab.yaml", "line 4", "Tabs"});
  ExpectErrorMentions(
      [] { (void)ReadOrbSettings(WriteFile("rgb.yaml", Appended(kOrbSlam2KittiStereo, "Camera.RGB: 2\n"))); },
      {"'Camera.RGB'"});
  std::string no_right = kOrbSlam2EurocStereo;
  no_right.erase(no_right.find("RIGHT.P:"));
  ExpectErrorMentions([&] { (void)ReadOrbSettings(WriteFile("noright.yaml", no_right)); }, {"'RIGHT.P'"});
  std::string distorted_rectified = kOrbSlam2EurocStereo;
  distorted_rectified.replace(distorted_rectified.find("Camera.k1: 0.0"), 14, "Camera.k1: 0.1");
  ExpectErrorMentions([&] { (void)ReadOrbSettings(WriteFile("k1blocks.yaml", distorted_rectified)); },
                      {"'Camera.k1'", "LEFT/RIGHT"});
  ExpectErrorMentions(
      [] {
        (void)ReadOrbSettings(WriteFile(
            "camera2.yaml",
            Appended(kOrbSlam2Mono, "Camera2.fx: 500\nCamera2.fy: 500\nCamera2.cx: 300\nCamera2.cy: 200\n")));
      },
      {"'Stereo.T_c1_c2'"});
}

// Raw images + the settings' rectification reproduce the EuRoC reader's own undistortion.
TEST(OrbSettings, EurocMonoUndistortsLikeTheEurocReader) {
  std::string mono = R"(%YAML:1.0
Camera.fx: 458.654
Camera.fy: 457.296
Camera.cx: 367.215
Camera.cy: 248.375
Camera.k1: -0.28340811
Camera.k2: 0.07395907
Camera.p1: 0.00019359
Camera.p2: 1.76187114e-05
Camera.width: 752
Camera.height: 480
Camera.fps: 20.0
)";
  DatasetOptions options;
  options.sensor = Sensor::kMonocular;
  const auto reference = OpenDataset(Euroc().string(), options);
  options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("euroc_mono.yaml", mono)));
  const auto dataset = OpenDataset(Euroc().string(), options);
  EXPECT_NE(dataset->name().find("calibration from euroc_mono.yaml"), std::string::npos) << dataset->name();
  const Calibration& a = dataset->calibration();
  const Calibration& b = reference->calibration();
  EXPECT_NEAR(a.camera.fx, b.camera.fx, 1e-9);
  EXPECT_NEAR(a.camera.cy, b.camera.cy, 1e-9);
  EXPECT_TRUE(a.T_body_cam.isApprox(b.T_body_cam));
  EXPECT_EQ(cv::norm(dataset->read(4).left, reference->read(4).left, cv::NORM_INF), 0);
  ASSERT_TRUE(dataset->ground_truth() && reference->ground_truth());
  EXPECT_TRUE(dataset->ground_truth()->back().T_world_cam.isApprox(reference->ground_truth()->back().T_world_cam));
}

// ORB-SLAM3's Camera2 + Stereo.T_c1_c2 rectify like the EuRoC reader (same stereoRectify inputs,
// up to T_c1_c2 written in float): T_c1_c2 is the pose of camera 2 in camera 1, not its inverse.
TEST(OrbSettings, OrbSlam3StereoRectifiesLikeTheEurocReader) {
  const auto reference = OpenDataset(Euroc().string());
  DatasetOptions options;
  options.settings =
      std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("euroc3_run.yaml", kOrbSlam3EurocStereo)));
  const auto dataset = OpenDataset(Euroc().string(), options);
  const Calibration& a = dataset->calibration();
  const Calibration& b = reference->calibration();
  EXPECT_EQ(a.sensor, Sensor::kStereo);
  EXPECT_NEAR(a.camera.fx, b.camera.fx, 0.05);
  EXPECT_NEAR(a.camera.cx, b.camera.cx, 0.05);
  EXPECT_NEAR(a.camera.cy, b.camera.cy, 0.05);
  EXPECT_NEAR(a.baseline_m, b.baseline_m, 1e-6);
  EXPECT_TRUE(a.T_body_cam.linear().isApprox(b.T_body_cam.linear(), 1e-4));
  const Frame fa = dataset->read(7), fb = reference->read(7);
  cv::Mat diff;
  cv::absdiff(fa.right, fb.right, diff);
  EXPECT_LT(cv::mean(diff)[0], 1.0);
}

// ORB-SLAM2's LEFT/RIGHT blocks: written from the EuRoC reader's own rectification, they give its
// images and calibration exactly.
TEST(OrbSettings, RectificationBlocksReproduceTheEurocReader) {
  const EurocDataset reference(Euroc());
  auto matrix = [](const std::string& name, int rows, int cols, const double* data) {
    std::string text = name + ": !!opencv-matrix\n   rows: " + std::to_string(rows) +
                       "\n   cols: " + std::to_string(cols) + "\n   dt: d\n   data: [";
    char number[64];
    for (int k = 0; k < rows * cols; ++k) {
      std::snprintf(number, sizeof(number), "%s%.17g", k ? ", " : "", data[k]);
      text += number;
    }
    return text + "]\n";
  };
  const cv::Matx34d& P0 = reference.rectified_projection(0);
  const cv::Matx34d& P1 = reference.rectified_projection(1);
  char header[512];
  std::snprintf(header, sizeof(header),
                "%%YAML:1.0\nCamera.fx: %.17g\nCamera.fy: %.17g\nCamera.cx: %.17g\nCamera.cy: %.17g\n"
                "Camera.width: 752\nCamera.height: 480\nCamera.bf: %.17g\n",
                P0(0, 0), P0(1, 1), P0(0, 2), P0(1, 2), -P1(0, 3));
  std::string text = header;
  for (int i = 0; i < 2; ++i) {
    const std::string block = i == 0 ? "LEFT" : "RIGHT";
    const EurocCameraModel& raw = reference.raw_camera(i);
    text += block + ".width: 752\n" + block + ".height: 480\n";
    text += matrix(block + ".K", 3, 3, raw.K.val);
    text += matrix(block + ".D", 1, 4, raw.distortion.val);
    text += matrix(block + ".R", 3, 3, reference.rectification_rotation(i).val);
    text += matrix(block + ".P", 3, 4, reference.rectified_projection(i).val);
  }
  DatasetOptions options;
  options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("blocks.yaml", text)));
  const auto dataset = OpenDataset(Euroc().string(), options);
  const Calibration& a = dataset->calibration();
  EXPECT_DOUBLE_EQ(a.camera.fx, reference.calibration().camera.fx);
  EXPECT_NEAR(a.baseline_m, reference.calibration().baseline_m, 1e-12);
  EXPECT_TRUE(a.T_body_cam.isApprox(reference.calibration().T_body_cam, 1e-12));
  const Frame fa = dataset->read(2), fb = reference.read(2);
  EXPECT_EQ(cv::norm(fa.left, fb.left, cv::NORM_INF), 0);
  EXPECT_EQ(cv::norm(fa.right, fb.right, cv::NORM_INF), 0);
}

TEST(OrbSettings, KittiCalibrationIsReplaced) {
  const fs::path kitti = testing::DatasetsDir() / "kitti/sequences/06";
  std::string text = kOrbSlam2KittiStereo;
  // KITTI 06's own images are 1226x370; a file for sequences 00-02 (1241x376) does not fit them.
  DatasetOptions options;
  options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("kitti00.yaml", text)));
  ExpectErrorMentions([&] { (void)OpenDataset(kitti.string(), options); },
                      {"kitti00.yaml", "Camera.width x Camera.height", "1241x376", "1226x370"});
  text.replace(text.find("Camera.width: 1241"), 18, "Camera.width: 1226");
  text.replace(text.find("Camera.height: 376"), 18, "Camera.height: 370");
  options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("kitti06.yaml", text)));
  const auto dataset = OpenDataset(kitti.string(), options);
  EXPECT_DOUBLE_EQ(dataset->calibration().camera.fx, 718.856);
  EXPECT_DOUBLE_EQ(dataset->calibration().baseline_m, 386.1448 / 718.856);
  EXPECT_EQ(dataset->calibration().frame_rate_hz, 10);
  EXPECT_EQ(dataset->size(), 51u);
  EXPECT_TRUE(dataset->ground_truth().has_value());
  // A file without a baseline cannot read a stereo sequence as stereo; monocular is fine.
  std::string mono = text;
  mono.erase(mono.find("Camera.bf: 386.1448"), 19);
  options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("kitti_mono.yaml", mono)));
  ExpectErrorMentions([&] { (void)OpenDataset(kitti.string(), options); }, {"kitti_mono.yaml", "baseline", "stereo"});
  options.sensor = Sensor::kMonocular;
  EXPECT_EQ(OpenDataset(kitti.string(), options)->calibration().sensor, Sensor::kMonocular);
  ExpectErrorMentions([&] { (void)OpenDataset("synth:room", options); }, {"synth:room", "settings"});
}

// TUM with settings: the settings' camera replaces camera.txt and DepthMapFactor scales the depth.
TEST(OrbSettings, TumDepthFactorAndCameraComeFromSettings) {
  const fs::path dir = testing::FreshTempDir("orb_settings_tum") / "seq";
  const auto scene = OpenDataset("synth:room:width=160,height=120,duration=0.2,sensor=rgbd");
  const fs::path path = WriteDataset(*scene, dir, DatasetFormat::kTum).dataset_path;
  const auto reference = OpenDataset(path.string());
  ASSERT_EQ(reference->calibration().sensor, Sensor::kRgbd);
  DatasetOptions options;
  options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(WriteFile("tum.yaml", R"(%YAML:1.0
Camera.fx: 130.0
Camera.fy: 131.0
Camera.cx: 80.5
Camera.cy: 60.5
Camera.fps: 30
Camera.bf: 10.4
DepthMapFactor: 1000.0
ThDepth: 40.0
)")));
  const auto dataset = OpenDataset(path.string(), options);
  EXPECT_EQ(dataset->calibration().camera.fx, 130);
  EXPECT_EQ(dataset->calibration().camera.width, 160);  // from the images
  EXPECT_EQ(dataset->calibration().frame_rate_hz, 30);
  EXPECT_EQ(dataset->calibration().baseline_m, 0);  // RGB-D: the virtual baseline is a SLAM option
  const Frame a = dataset->read(1), b = reference->read(1);
  EXPECT_EQ(cv::norm(a.left, b.left, cv::NORM_INF), 0);
  cv::Mat scaled = b.depth * 5.0;  // written at 5000 units per metre, read at 1000
  EXPECT_LT(cv::norm(a.depth, scaled, cv::NORM_INF), 1e-4);
}

// A refinement found on images another refinement gave composes with it into one: the pixel the
// two put a point at (the second on the first's undistorted camera, the first on the dataset's)
// is the one the composed refinement puts it at, to the neglected second-order term.
TEST(CameraRefit, TwoRefinementsComposeIntoOne) {
  const double fx = 707;  // KITTI's camera, its farthest corner at about (0.87, 0.26)
  const CameraRefit first{1.006, 0.019}, second{0.998, 0.004};
  const CameraRefit both = ThenRefit(first, second);
  EXPECT_DOUBLE_EQ(both.focal_scale, 1.006 * 0.998);
  double worst = 0;
  for (double x = 0; x <= 0.87; x += 0.029)
    for (double y = 0; y <= 0.26; y += 0.026) {
      const double rt2 = x * x + y * y;
      // The second model: the first's undistorted image shows the point at s_b x (1 + k_b r^2).
      const double g = second.focal_scale * (1 + second.k1 * rt2);
      const double xu = g * x, yu = g * y;
      // The first: the dataset's image shows that at fx s_a xu (1 + k_a |xu|^2).
      const double f = fx * first.focal_scale * (1 + first.k1 * (xu * xu + yu * yu));
      const double c = fx * both.focal_scale * (1 + both.k1 * rt2);
      worst = std::max(worst, std::hypot(f * xu - c * x, f * yu - c * y));
    }
  EXPECT_LT(worst, 0.15);
  EXPECT_GT(worst, 0.01);  // the second-order term is there: the composition is to first order
  // Refining nothing changes nothing.
  const CameraRefit same = ThenRefit(first, CameraRefit{});
  EXPECT_DOUBLE_EQ(same.focal_scale, first.focal_scale);
  EXPECT_DOUBLE_EQ(same.k1, first.k1);
}

// A refinement's camera is the one ApplyCameraRefit gives, its pixels sit where the undistortion
// maps sample the given image, and two refinements of one camera map pixels into each other.
TEST(RefinedCamera, PixelsMoveBetweenRefinementsOfOneCamera) {
  DatasetOptions options;
  options.sensor = Sensor::kMonocular;
  const std::string scene = "synth:room:width=480,height=360,duration=0.2";
  const PinholeCamera given = OpenDataset(scene, options)->calibration().camera;
  const CameraRefit a{1.012, 0.03}, b{0.995, -0.01}, focal_only{1.02, 0};
  std::vector<Eigen::Vector2d> grid;
  for (double u = 0; u < given.width; u += given.width / 12.0)
    for (double v = 0; v < given.height; v += given.height / 9.0) grid.emplace_back(u, v);
  for (const CameraRefit& refit : {a, b, focal_only, CameraRefit{}}) {
    const RefinedCamera refined(given, refit);
    const PinholeCamera through = ApplyCameraRefit(OpenDataset(scene, options), refit)->calibration().camera;
    EXPECT_DOUBLE_EQ(refined.camera().fx, through.fx);
    EXPECT_DOUBLE_EQ(refined.camera().fy, through.fy);
    EXPECT_DOUBLE_EQ(refined.camera().cx, through.cx);
    EXPECT_DOUBLE_EQ(refined.camera().cy, through.cy);
    EXPECT_EQ(refined.camera().width, through.width);
    // The maps the refined images are resampled with.
    const cv::Matx33d lens(given.fx * refit.focal_scale, 0, given.cx, 0, given.fy * refit.focal_scale, given.cy, 0,
                           0, 1);
    const cv::Matx33d undistorted(through.fx, 0, through.cx, 0, through.fy, through.cy, 0, 0, 1);
    cv::Mat map_u, map_v;
    cv::initUndistortRectifyMap(lens, cv::Mat(cv::Vec4d(refit.k1, 0, 0, 0)), cv::Mat::eye(3, 3, CV_64F),
                                undistorted, cv::Size(given.width, given.height), CV_32FC1, map_u, map_v);
    const std::vector<Eigen::Vector2d> in_given = refined.ToGiven(grid);
    const std::vector<Eigen::Vector2d> back = refined.FromGiven(in_given);
    ASSERT_EQ(in_given.size(), grid.size());
    double worst_map = 0, worst_round_trip = 0;
    for (size_t i = 0; i < grid.size(); ++i) {
      const int u = static_cast<int>(grid[i].x()), v = static_cast<int>(grid[i].y());
      const Eigen::Vector2d at(u, v);
      const Eigen::Vector2d sampled(map_u.at<float>(v, u), map_v.at<float>(v, u));
      worst_map = std::max(worst_map, (refined.ToGiven(std::vector{at})[0] - sampled).norm());
      worst_round_trip = std::max(worst_round_trip, (back[i] - grid[i]).norm());
    }
    EXPECT_LT(worst_map, 1e-3) << refit.k1;
    EXPECT_LT(worst_round_trip, 1e-6) << refit.k1;
  }
  // Nothing refined: the given camera, pixels unmoved.
  const std::vector<Eigen::Vector2d> same = RefinedCamera(given, CameraRefit{}).ToGiven(grid);
  for (size_t i = 0; i < grid.size(); ++i) EXPECT_LT((same[i] - grid[i]).norm(), 1e-9);
  // From a to b and back; a into itself changes nothing; a and b differ by pixels at the corners.
  const RefinedCamera ra(given, a), rb(given, b);
  const std::vector<Eigen::Vector2d> in_b = Reexpress(ra, rb, grid), again = Reexpress(rb, ra, in_b),
                                     self = Reexpress(ra, ra, grid);
  double largest = 0;
  for (size_t i = 0; i < grid.size(); ++i) {
    EXPECT_LT((again[i] - grid[i]).norm(), 1e-6);
    EXPECT_LT((self[i] - grid[i]).norm(), 1e-6);
    largest = std::max(largest, (in_b[i] - grid[i]).norm());
  }
  EXPECT_GT(largest, 2.0);
  EXPECT_TRUE(Reexpress(ra, rb, std::vector<Eigen::Vector2d>{}).empty());
}

}  // namespace
}  // namespace flatslam
