// flatslam run --save-map and flatslam map info/verify/export: outputs and exit codes, on a good
// snapshot and on bad ones (missing, truncated, flipped, wrong type).
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <sys/wait.h>

#include "cli.h"
#include "io/orb_settings.h"
#include "trajectory/trajectory_io.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::Contains;
using testing::RunApp;
using Result = testing::CliResult;
using testing::NumberAfter;
using testing::ReadBytes;

void WriteText(const fs::path& path, const std::string& text) {
  std::ofstream out(path, std::ios::binary);
  out << text;
}

class MapCli : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = testing::FreshTempDir("map_cli");
    run_ =
        RunApp("run synth:room:duration=6,width=480,height=360 --deterministic --quiet --vocabulary none --save-map " +
               (dir_ / "room.fsmap").string());
  }
  static void TearDownTestSuite() { fs::remove_all(dir_); }
  static fs::path dir_;
  static Result run_;
};
fs::path MapCli::dir_;
Result MapCli::run_;

TEST_F(MapCli, RunSavesAMapThatVerifies) {
  ASSERT_EQ(run_.exit_code, 0) << run_.output;
  EXPECT_TRUE(Contains(run_.output, "map snapshot")) << run_.output;
  ASSERT_TRUE(fs::exists(dir_ / "room.fsmap"));
  const Result r = RunApp("map verify " + (dir_ / "room.fsmap").string());
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "ok")) << r.output;
  // The rig as the saved map measures it: the figure the run printed from the same map.
  auto offset = [](const std::string& output, const std::string& key) {
    const size_t at = output.find(key);
    return at == std::string::npos ? std::string("none") : output.substr(at + key.size(), 6);
  };
  EXPECT_NE(offset(r.output, "stereo rig    map 0: disparities "), "none") << r.output;
  EXPECT_EQ(offset(r.output, "stereo rig    map 0: disparities "), offset(run_.output, "stereo rig    disparities "))
      << r.output << run_.output;
}

TEST_F(MapCli, InfoPrintsCountsAgentsBoundsAndVersion) {
  const Result r = RunApp("map info " + (dir_ / "room.fsmap").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  for (const char* part :
       {"format        version 1", "vocabulary    checksum 0000000000000000 (none)", "maps          1", "agents [0]",
        "keyframes", "map points", "bounding box [", "MiB", "sensor        stereo"})
    EXPECT_TRUE(Contains(r.output, part)) << part << " missing in:\n" << r.output;
}

TEST_F(MapCli, ExportWritesPlyAndTumTrajectory) {
  const fs::path ply = dir_ / "points.ply", tum = dir_ / "traj.tum", bin = dir_ / "points_bin.ply";
  Result r = RunApp("map export " + (dir_ / "room.fsmap").string() + " --ply " + ply.string() + " --trajectory " +
                    tum.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const std::string header = ReadBytes(ply);
  ASSERT_TRUE(Contains(header, "ply\nformat ascii 1.0\n")) << header.substr(0, 200);
  const size_t count_at = header.find("element vertex ");
  ASSERT_NE(count_at, std::string::npos);
  const size_t vertices = std::stoul(header.substr(count_at + 15));
  EXPECT_GT(vertices, 100u);
  const std::string body = header.substr(header.find("end_header\n") + 11);
  EXPECT_EQ(static_cast<size_t>(std::count(body.begin(), body.end(), '\n')), vertices);

  std::istringstream lines(ReadBytes(tum));
  std::string line;
  double last_t = -1;
  size_t poses = 0;
  while (std::getline(lines, line)) {
    if (line.empty() || line[0] == '#') continue;
    std::istringstream fields(line);
    std::vector<double> v{std::istream_iterator<double>(fields), {}};
    ASSERT_EQ(v.size(), 8u) << line;
    EXPECT_GT(v[0], last_t);
    last_t = v[0];
    ++poses;
  }
  EXPECT_GT(poses, 3u);

  // The same keyframe trajectory as KITTI (with its times) and EuRoC csv.
  const Trajectory from_tum = ReadTum(tum);
  for (const char* format : {"kitti", "euroc"}) {
    const fs::path file = dir_ / (std::string("traj.") + format);
    r = RunApp("map export " + (dir_ / "room.fsmap").string() + " --trajectory " + file.string() + " --format " +
               format);
    ASSERT_EQ(r.exit_code, 0) << r.output;
    const Trajectory back = std::string(format) == "kitti"
                                ? ReadKitti(file, ReadKittiTimes(file.string() + ".times.txt"))
                                : ReadEuroc(file);
    ASSERT_EQ(back.size(), from_tum.size()) << format;
    for (size_t i = 0; i < back.size(); ++i) {
      EXPECT_NEAR(static_cast<double>(back[i].t_ns), static_cast<double>(from_tum[i].t_ns), 1e3) << format << i;
      EXPECT_LT((back[i].T_world_cam.matrix() - from_tum[i].T_world_cam.matrix()).cwiseAbs().maxCoeff(), 1e-9)
          << format << " pose " << i;
    }
  }
  r = RunApp("map export " + (dir_ / "room.fsmap").string() + " --trajectory " + tum.string() + " --format csv");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "--format is tum, kitti or euroc")) << r.output;

  r = RunApp("map export " + (dir_ / "room.fsmap").string() + " --ply " + bin.string() + " --ply-format binary");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const std::string binary = ReadBytes(bin);
  const size_t data_at = binary.find("end_header\n") + 11;
  EXPECT_TRUE(Contains(binary.substr(0, data_at), "binary_little_endian"));
  EXPECT_EQ(binary.size() - data_at, vertices * 12);
}

TEST_F(MapCli, ExportWritesAColmapModelThatColmapReadsWithTheMapsCounts) {
  const fs::path model = dir_ / "colmap" / "room";  // created by the export
  Result r = RunApp("map export " + (dir_ / "room.fsmap").string() + " --colmap " + model.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  const std::string wrote = r.output;
  EXPECT_TRUE(Contains(wrote, "wrote " + model.string() + ": map 0, ")) << wrote;
  for (const char* file : {"cameras.txt", "images.txt", "points3D.txt"}) EXPECT_TRUE(fs::exists(model / file)) << file;
  const double images = NumberAfter(wrote, "map 0, "), points = NumberAfter(wrote, "images, ");
  const double observations = NumberAfter(wrote, "points, ");
  const double unobserved = Contains(wrote, "without observations") ? NumberAfter(wrote, "px (") : 0;

  // The same numbers as the snapshot: keyframes, observations, and map points with observations.
  r = RunApp("map info " + (dir_ / "room.fsmap").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_GT(images, 1);
  EXPECT_EQ(images, NumberAfter(r.output, "agents [0], ")) << wrote << r.output;
  EXPECT_EQ(points + unobserved, NumberAfter(r.output, "keyframes, ")) << wrote << r.output;
  EXPECT_EQ(observations, NumberAfter(r.output, "map points, ")) << wrote << r.output;

  // A directory that cannot be made is an error naming it, after nothing was written.
  r = RunApp("map export " + (dir_ / "room.fsmap").string() + " --colmap " + (dir_ / "room.fsmap" / "m").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, (dir_ / "room.fsmap" / "m").string())) << r.output;

  if (!fs::exists("/usr/bin/colmap")) GTEST_SKIP() << "/usr/bin/colmap not installed";
  r = testing::RunCommand("/usr/bin/colmap model_analyzer --path " + model.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_EQ(NumberAfter(r.output, "Registered images: "), images) << r.output;
  EXPECT_EQ(NumberAfter(r.output, "Points: "), points) << r.output;
  EXPECT_EQ(NumberAfter(r.output, "Observations: "), observations) << r.output;
}

TEST_F(MapCli, BadFilesFailWithTheProblemNamed) {
  const std::string good = ReadBytes(dir_ / "room.fsmap");
  ASSERT_GT(good.size(), 1000u);
  WriteText(dir_ / "cut.fsmap", good.substr(0, good.size() / 2));
  std::string flipped = good;
  flipped[flipped.size() / 3] ^= 0x10;
  WriteText(dir_ / "flipped.fsmap", flipped);
  WriteText(dir_ / "notes.txt", "just some text, long enough to have an identifier\n");

  Result r = RunApp("map verify " + (dir_ / "nowhere.fsmap").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "cannot open")) << r.output;
  r = RunApp("map verify " + (dir_ / "cut.fsmap").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "cut.fsmap") && Contains(r.output, "corrupt")) << r.output;
  r = RunApp("map verify " + (dir_ / "flipped.fsmap").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "flipped.fsmap")) << r.output;
  EXPECT_FALSE(Contains(r.output, "ok:")) << r.output;
  r = RunApp("map info " + (dir_ / "notes.txt").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "not a flatslam map snapshot")) << r.output;
  r = RunApp("map verify " + (dir_ / "room.fsmap").string() + " --vocabulary-checksum 5");
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "vocabulary")) << r.output;
  r = RunApp("map export " + (dir_ / "cut.fsmap").string() + " --ply " + (dir_ / "x.ply").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_FALSE(fs::exists(dir_ / "x.ply"));
}

// The camera check on a monocular map of a rendered room, whose camera is exact: it agrees, and
// the settings file it writes reads back with the refined camera; seen through a lens the
// calibration leaves out, it disagrees and names the lens's k1. A stereo map gets its check
// printed but no settings file (a distorted pair would need its rectification).
TEST_F(MapCli, CalibrateChecksTheCameraAndWritesSettings) {
  const fs::path mono = dir_ / "room_mono.fsmap", settings = dir_ / "refined.yaml";
  Result r = RunApp("run synth:room:duration=6,width=480,height=360 --sensor mono --deterministic --quiet "
                    "--vocabulary none --save-map " + mono.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunApp("map calibrate " + mono.string() + " --settings-out " + settings.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "agree with the camera model")) << r.output;
  const double fx = NumberAfter(r.output, "s): fx ");
  EXPECT_NEAR(fx, 360, 3.6) << r.output;  // the scene renders with fx 0.75 x 480
  ASSERT_TRUE(fs::exists(settings));
  const OrbSettings read = ReadOrbSettings(settings);
  EXPECT_NEAR(read.camera.fx, fx, 0.01);
  EXPECT_NEAR(read.camera.fy, fx, 0.01);
  EXPECT_LT(std::abs(read.camera.distortion[0]), 0.01);

  // The same room seen through a lens the calibration leaves out (k1 = 0.03), the camera kept as
  // given: the check finds the lens.
  const fs::path lens = dir_ / "room_lens.fsmap";
  const std::string lens_run = "run synth:room:duration=8,width=480,height=360,k1=0.03 --sensor mono --deterministic "
                               "--quiet --vocabulary none --save-map " + lens.string();
  const fs::path lens_out = dir_ / "room_lens";
  r = RunApp(lens_run + " --keep-camera --out " + lens_out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_FALSE(Contains(r.output, "started over")) << r.output;
  r = RunApp("map calibrate " + lens.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "disagree with the camera model")) << r.output;
  EXPECT_NEAR(NumberAfter(r.output, "k1 +"), 0.03, 0.008) << r.output;
  // -o: the map re-expressed in the camera it asks for and adjusted in it. Its keyframes shed
  // what they had bent to fit the wrong model (Sim(3) ATE of the keyframes against the rendered
  // poses: 0.0206 -> 0.0046 m when written), the map verifies, and its own check agrees.
  const fs::path relens = dir_ / "room_lens_refined.fsmap";
  r = RunApp("map calibrate " + lens.string() + " -o " + relens.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "keypoints into the refined camera")) << r.output;
  EXPECT_EQ(RunApp("map verify " + relens.string()).exit_code, 0);
  r = RunApp("map calibrate " + relens.string());
  EXPECT_TRUE(Contains(r.output, "agree with the camera model")) << r.output;
  const fs::path relens_keyframes = dir_ / "room_lens_refined.tum";
  ASSERT_EQ(RunApp("map export " + relens.string() + " --trajectory " + relens_keyframes.string()).exit_code, 0);
  auto keyframe_ate = [&](const fs::path& keyframes) {
    const Result eval =
        RunApp("eval " + keyframes.string() + " " + (lens_out / "groundtruth.tum").string() + " --align sim3");
    EXPECT_EQ(eval.exit_code, 0) << eval.output;
    return NumberAfter(eval.output, "ATE [m]");
  };
  const double kept_ate = keyframe_ate(lens_out / "keyframes.tum"), refined_ate = keyframe_ate(relens_keyframes);
  EXPECT_LT(refined_ate, 0.5 * kept_ate) << kept_ate << " -> " << refined_ate;
  // By default the run finds it itself, starts over with the refined camera, and saves the map
  // with that camera: its own check then agrees, and a session continuing the map on the same
  // dataset sees it through that camera (the shipped vocabulary: continuing needs one).
  const std::string lens_default = "run synth:room:duration=8,width=480,height=360,k1=0.03 --sensor mono --quiet ";
  r = RunApp(lens_default + "--save-map " + lens.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "the run started over with k1 +")) << r.output;
  r = RunApp("map calibrate " + lens.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "agree with the camera model")) << r.output;
  EXPECT_FALSE(Contains(r.output, "(given 360.00")) << r.output;  // the refined camera is the map's
  r = RunApp(lens_default + "--max-frames 40 --load-map " + lens.string());
  EXPECT_EQ(r.exit_code, 0) << r.output;
  EXPECT_FALSE(Contains(r.output, "another camera")) << r.output;

  r = RunApp("map calibrate " + (dir_ / "room.fsmap").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "camera        map 0")) << r.output;
  r = RunApp("map calibrate " + (dir_ / "room.fsmap").string() + " --settings-out " + (dir_ / "no.yaml").string());
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_TRUE(Contains(r.output, "holds a stereo map")) << r.output;
  EXPECT_FALSE(fs::exists(dir_ / "no.yaml"));
  r = RunApp("map calibrate " + (dir_ / "room.fsmap").string() + " -o " + (dir_ / "no.fsmap").string());
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_TRUE(Contains(r.output, "-o refines a monocular camera")) << r.output;
  EXPECT_FALSE(fs::exists(dir_ / "no.fsmap"));
}

TEST_F(MapCli, UsageErrors) {
  Result r = RunApp("map");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  r = RunApp("map frobnicate x");
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_TRUE(Contains(r.output, "unknown map subcommand")) << r.output;
  r = RunApp("map export " + (dir_ / "room.fsmap").string());
  EXPECT_EQ(r.exit_code, 2) << r.output;
  r = RunApp("map --help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_TRUE(Contains(r.output, "usage: flatslam map info FILE")) << r.output;
  r = RunApp("run synth:room:duration=1 --vocabulary none --save-map " + (dir_ / "missing_dir" / "m.fsmap").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "does not exist")) << r.output;
}

}  // namespace
}  // namespace flatslam
