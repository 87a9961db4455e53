// End-to-end checks of flatslam run/info with an ORB-SLAM2/3 settings file (--settings): a plain
// folder of rendered stereo images tracks, and a missing or wrong settings file is named.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>

#include "cli.h"
#include "io/synthetic.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;
using testing::Contains;
using testing::RunApp;

// 60 stereo frames (3 s at 20 Hz) of the room scene as left/ + right/ PNGs, and a settings file
// describing the camera.
struct StereoFolder {
  fs::path dir, settings;
};

const StereoFolder& RenderedFolder() {
  static const StereoFolder folder = [] {
    StereoFolder f;
    const fs::path root = testing::FreshTempDir("settings_cli");
    f.dir = root / "room";
    f.settings = root / "room.yaml";
    SyntheticOptions options;
    options.frame_rate_hz = 20;
    options.duration_s = 3;
    options.sensor = Sensor::kStereo;
    const SyntheticScene scene(MakeScene("room"), options);
    fs::create_directories(f.dir / "left");
    fs::create_directories(f.dir / "right");
    for (size_t i = 0; i < scene.frame_count(); ++i) {
      const Frame frame = scene.Render(i);
      char name[32];
      std::snprintf(name, sizeof(name), "%06zu.png", i);
      cv::imwrite((f.dir / "left" / name).string(), frame.left);
      cv::imwrite((f.dir / "right" / name).string(), frame.right);
    }
    const Calibration& c = scene.calibration();
    char text[1024];
    std::snprintf(text, sizeof(text),
                  "%%YAML:1.0\n# Camera of the rendered room scene\nCamera.fx: %.17g\nCamera.fy: %.17g\n"
                  "Camera.cx: %.17g\nCamera.cy: %.17g\nCamera.k1: 0.0\nCamera.k2: 0.0\nCamera.p1: 0.0\n"
                  "Camera.p2: 0.0\nCamera.width: %d\nCamera.height: %d\nCamera.fps: 20.0\nCamera.bf: %.17g\n"
                  "Camera.RGB: 1\nThDepth: 35\nORBextractor.nFeatures: 1000\nORBextractor.scaleFactor: 1.2\n"
                  "ORBextractor.nLevels: 8\nORBextractor.iniThFAST: 20\nORBextractor.minThFAST: 7\n"
                  "Viewer.KeyFrameSize: 0.05\nViewer.PointSize: 2\n",
                  c.camera.fx, c.camera.fy, c.camera.cx, c.camera.cy, c.camera.width, c.camera.height,
                  c.baseline_m * c.camera.fx);
    std::ofstream(f.settings) << text;
    return f;
  }();
  return folder;
}

TEST(SettingsCli, StereoImageFolderTracksEveryFrame) {
  const StereoFolder& f = RenderedFolder();
  const auto r = RunApp("run " + f.dir.string() + " --settings " + f.settings.string() + " --sensor stereo --quiet");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "images room (stereo), calibration from room.yaml")) << r.output;
  EXPECT_TRUE(Contains(r.output, "60 tracked, 0 lost")) << r.output;
  // The settings are the folder's only calibration: nothing is said to be replaced.
  EXPECT_FALSE(Contains(r.output, "replaces the dataset's calibration")) << r.output;
}

TEST(SettingsCli, InfoDescribesTheFolder) {
  const StereoFolder& f = RenderedFolder();
  const auto r = RunApp("info " + f.dir.string() + " --settings " + f.settings.string() + " --check");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "camera     640x480, fx 480.000")) << r.output;
  EXPECT_TRUE(Contains(r.output, "baseline 0.1200 m")) << r.output;
  EXPECT_TRUE(Contains(r.output, "frames     60, 2.950 s (nominal 20.0 Hz)")) << r.output;
  EXPECT_TRUE(Contains(r.output, "all 60 frames read")) << r.output;
}

TEST(SettingsCli, FolderWithoutSettingsAsksForThem) {
  const StereoFolder& f = RenderedFolder();
  const auto r = RunApp("run " + f.dir.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "plain image folder")) << r.output;
  EXPECT_TRUE(Contains(r.output, "needs a camera settings file (--settings FILE")) << r.output;
}

TEST(SettingsCli, UnknownKeyIsNamed) {
  const StereoFolder& f = RenderedFolder();
  const fs::path bad = f.settings.parent_path() / "bad.yaml";
  std::ofstream(bad) << testing::ReadBytes(f.settings) << "Camera.fxx: 480.0\n";
  const auto r = RunApp("run " + f.dir.string() + " --settings " + bad.string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "settings file " + bad.string() + ": unknown key 'Camera.fxx'")) << r.output;
}

// A real sequence keeps its images and ground truth; the settings' camera and ORB options apply.
TEST(SettingsCli, KittiCalibrationIsReplacedAndSaid) {
  const fs::path settings = RenderedFolder().settings.parent_path() / "kitti06.yaml";
  std::ofstream(settings) << "%YAML:1.0\nCamera.fx: 707.0912\nCamera.fy: 707.0912\nCamera.cx: 601.8873\n"
                             "Camera.cy: 183.1104\nCamera.width: 1226\nCamera.height: 370\nCamera.fps: 10.0\n"
                             "Camera.bf: 379.8145\nThDepth: 40\nORBextractor.nFeatures: 1500\n";
  const std::string sequence = (testing::DatasetsDir() / "kitti/sequences/06").string();
  auto r = RunApp("run " + sequence + " --settings " + settings.string() + " --list-options");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "settings " + settings.string() + " replaces the dataset's calibration")) << r.output;
  EXPECT_TRUE(Contains(r.output, "orb.features = 1500")) << r.output;
  EXPECT_TRUE(Contains(r.output, "close_depth_baselines = 40")) << r.output;
  // --set wins over the settings file.
  r = RunApp("run " + sequence + " --settings " + settings.string() + " --set orb.features=900 --list-options");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "orb.features = 900")) << r.output;
}

}  // namespace
}  // namespace flatslam
