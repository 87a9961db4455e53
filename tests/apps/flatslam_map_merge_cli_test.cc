// flatslam map merge: overlapping maps join, a map of another place stays separate, inputs are
// never modified, sessions that refined one camera differently merge in the first one's camera,
// and mismatched calibration or vocabulary, a missing vocabulary and an output that is an input
// are refused with one clear error and nothing written.
#include <algorithm>
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>

#include <gtest/gtest.h>
#include <sys/wait.h>

#include "cli.h"
#include "report/results.h"
#include "storage/snapshot.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

using testing::Contains;
using testing::RunApp;
using Result = testing::CliResult;
using testing::ReadBytes;

class MapMergeCli : public ::testing::Test {
 protected:
  // Two runs of the room (same path, different image noise: they overlap everywhere), the street
  // with the room's stereo baseline (same calibration, another place), the room at another
  // resolution and the room without a vocabulary.
  static void SetUpTestSuite() {
    dir_ = testing::FreshTempDir("map_merge_cli");
    const std::string common = " --deterministic --quiet --save-map ";
    setup_ =
        RunApp("run synth:room:duration=6,width=480,height=360 --agent 0" + common + path("room1")).output +
        RunApp("run synth:room:duration=6,width=480,height=360,seed=2 --agent 1" + common + path("room2")).output +
        RunApp("run synth:street:duration=6,width=480,height=360,baseline=0.12 --agent 2" + common + path("street"))
            .output +
        RunApp("run synth:room:duration=3,width=640,height=480" + common + path("room640")).output +
        RunApp("run synth:room:duration=3,width=480,height=360 --vocabulary none" + common + path("novocab")).output;
  }
  static void TearDownTestSuite() { fs::remove_all(dir_); }
  static std::string path(const std::string& name) { return (dir_ / (name + ".fsmap")).string(); }
  static fs::path dir_;
  static std::string setup_;

  void RefusesAnotherCalibration();
  void RefusesAnotherVocabulary();
  void RefusesToOverwriteAnInput();
};
fs::path MapMergeCli::dir_;
std::string MapMergeCli::setup_;

TEST_F(MapMergeCli, JoinsOverlappingMapsAndKeepsOthersApart) {
  for (const char* name : {"room1", "room2", "street"}) ASSERT_TRUE(fs::exists(path(name))) << setup_;
  const std::string before1 = ReadBytes(path("room1")), before2 = ReadBytes(path("room2")),
                    before3 = ReadBytes(path("street"));
  const Result r =
      RunApp("map merge " + path("room1") + " " + path("room2") + " " + path("street") + " -o " + path("merged"));
  ASSERT_EQ(r.exit_code, 0) << r.output;
  for (const char* part : {"overlap       0-1: found", "overlap       0-2: none", "overlap       1-2: none",
                           "pairs verified", "transform", "points fused", "output map 0   inputs 0+1, agents [0,1]",
                           "output map 1   inputs 2, agents [2]", "kept separate", "2 maps", "time"})
    EXPECT_TRUE(Contains(r.output, part)) << part << "\n" << r.output;
  // One try only: the street overlaps nothing, so no merge with it is attempted.
  EXPECT_EQ(r.output.find("try "), r.output.rfind("try ")) << r.output;
  EXPECT_EQ(ReadBytes(path("room1")), before1);
  EXPECT_EQ(ReadBytes(path("room2")), before2);
  EXPECT_EQ(ReadBytes(path("street")), before3);
  const Result verify = RunApp("map verify " + path("merged"));
  EXPECT_EQ(verify.exit_code, 0) << verify.output;
  const Result info = RunApp("map info " + path("merged"));
  EXPECT_TRUE(Contains(info.output, "maps          2")) << info.output;
  EXPECT_TRUE(Contains(info.output, "agents [0,1]")) << info.output;

  // Each agent's keyframes exported on their own add up to the merged map's.
  auto poses = [&](const std::string& agent) {
    const std::string file = (dir_ / ("poses" + agent + ".tum")).string();
    const Result e =
        RunApp("map export " + path("merged") + " --trajectory " + file + (agent.empty() ? "" : " --agent " + agent));
    EXPECT_EQ(e.exit_code, 0) << e.output;
    std::ifstream in(file);
    size_t count = 0;
    for (std::string line; std::getline(in, line);) count += !line.empty() && line[0] != '#';
    return count;
  };
  const size_t agent0 = poses("0"), agent1 = poses("1"), agent2 = poses("2");
  EXPECT_GT(agent0, 10u);
  EXPECT_GT(agent1, 10u);
  EXPECT_GT(agent2, 0u);  // the street, a map of its own in the same file
  EXPECT_EQ(agent0 + agent1 + agent2, poses(""));
  const Result none =
      RunApp("map export " + path("merged") + " --trajectory " + (dir_ / "none.tum").string() + " --agent 7");
  EXPECT_NE(none.exit_code, 0);
  EXPECT_TRUE(Contains(none.output, "no keyframes of agent 7 (its maps hold agents [0,1,2])")) << none.output;
  EXPECT_FALSE(fs::exists(dir_ / "none.tum"));

  // The merged map was adjusted as a whole (two iterations); the street, merged with nothing, was not.
  EXPECT_TRUE(Contains(r.output, "\nadjusted      map 0: ")) << r.output;
  EXPECT_FALSE(Contains(r.output, "\nadjusted      map 1: ")) << r.output;
  EXPECT_FALSE(Contains(r.output, "(refine: full passes)")) << r.output;
  // --refine runs that adjustment to convergence; --close-loops searches the merged map for loops
  // (the plain merge above did not).
  EXPECT_FALSE(Contains(r.output, "\nloops ")) << r.output;
  const Result refined =
      RunApp("map merge " + path("room1") + " " + path("room2") + " --refine --close-loops -o " + path("refined"));
  ASSERT_EQ(refined.exit_code, 0) << refined.output;
  EXPECT_TRUE(Contains(refined.output, "\nadjusted      map 0: ")) << refined.output;
  EXPECT_TRUE(Contains(refined.output, "(refine: full passes)")) << refined.output;
  EXPECT_TRUE(Contains(refined.output, "\nloops         map 0: ")) << refined.output;
  EXPECT_EQ(RunApp("map verify " + path("refined")).exit_code, 0);
}

// ctest runs every test in its own process, and the set-up makes five SLAM runs: the refusals
// share one test so the set-up runs twice in all, not four times.
TEST_F(MapMergeCli, RefusesMismatchedInputsAndOverwrites) {
  {
    SCOPED_TRACE("another calibration");
    RefusesAnotherCalibration();
  }
  {
    SCOPED_TRACE("another vocabulary");
    RefusesAnotherVocabulary();
  }
  {
    SCOPED_TRACE("output is an input");
    RefusesToOverwriteAnInput();
  }
}

void MapMergeCli::RefusesAnotherCalibration() {
  ASSERT_TRUE(fs::exists(path("room640"))) << setup_;
  const Result r = RunApp("map merge " + path("room1") + " " + path("room640") + " -o " + path("out_calib"));
  EXPECT_NE(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "calibration")) << r.output;
  EXPECT_FALSE(fs::exists(path("out_calib")));

  // One camera, two monocular sessions: one refined the camera from its own map, one kept it.
  // Their keypoints do not share a camera: the second's move into the first's through the camera
  // both were given, and the maps merge into one that fits its keypoints to under a pixel.
  const std::string lens = "run synth:room:duration=8,width=480,height=360,k1=0.03 --sensor mono --deterministic "
                           "--quiet --vocabulary none --save-map ";
  Result run = RunApp(lens + path("lens_refined"));
  ASSERT_EQ(run.exit_code, 0) << run.output;
  ASSERT_TRUE(Contains(run.output, "the run started over")) << run.output;
  run = RunApp(lens + path("lens_kept") + " --keep-camera");
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const Result mixed =
      RunApp("map merge " + path("lens_refined") + " " + path("lens_kept") + " -o " + path("out_lens"));
  ASSERT_EQ(mixed.exit_code, 0) << mixed.output;
  EXPECT_TRUE(Contains(mixed.output, "lens_kept.fsmap#0: keypoints from the camera as given into ")) << mixed.output;
  EXPECT_TRUE(Contains(mixed.output, "refined from its own map: k1 +0.0")) << mixed.output;
  EXPECT_TRUE(Contains(mixed.output, "output map 0   inputs 0+1")) << mixed.output;
  EXPECT_EQ(RunApp("map verify " + path("out_lens")).exit_code, 0);
  const Result exported = RunApp("map export " + path("out_lens") + " --colmap " + (dir_ / "lens_colmap").string());
  ASSERT_EQ(exported.exit_code, 0) << exported.output;
  const size_t at = exported.output.find("mean reprojection error ");
  ASSERT_NE(at, std::string::npos) << exported.output;
  EXPECT_LT(std::stod(exported.output.substr(at + 24)), 1.0) << exported.output;
  // A later session run with the first one's camera: the maps share it and merge.
  run = RunApp(lens + path("lens_shared") + " --camera-from " + path("lens_refined"));
  ASSERT_EQ(run.exit_code, 0) << run.output;
  EXPECT_FALSE(Contains(run.output, "camera check")) << run.output;  // not checked again
  const Result shared =
      RunApp("map merge " + path("lens_refined") + " " + path("lens_shared") + " -o " + path("out_shared"));
  EXPECT_EQ(shared.exit_code, 0) << shared.output;
  EXPECT_TRUE(fs::exists(path("out_shared")));
  // Its map records that camera, so a third session can take it from either.
  run = RunApp(lens + path("lens_third") + " --max-frames 20 --camera-from " + path("lens_shared"));
  EXPECT_EQ(run.exit_code, 0) << run.output;
  // A map of another camera, and a stereo run, are refused naming the file.
  run = RunApp("run synth:room:duration=2,width=640,height=480 --sensor mono --quiet --vocabulary none --camera-from " +
               path("lens_refined"));
  EXPECT_NE(run.exit_code, 0) << run.output;
  EXPECT_TRUE(Contains(run.output, "another camera")) << run.output;
  EXPECT_TRUE(Contains(run.output, "lens_refined")) << run.output;
  run = RunApp("run synth:room:duration=2,width=480,height=360 --sensor stereo --quiet --camera-from " +
               path("lens_refined"));
  EXPECT_NE(run.exit_code, 0) << run.output;
  EXPECT_TRUE(Contains(run.output, "only monocular")) << run.output;
  // A batch takes a map's camera for its sequences the same way, and its rows say which camera.
  run = RunApp("batch synth:room:duration=4,width=480,height=360,k1=0.03 --sensor mono --quiet --vocabulary none "
               "--out " + (dir_ / "batch_lens").string() + " --camera-from " + path("lens_refined"));
  ASSERT_EQ(run.exit_code, 0) << run.output;
  const std::vector<SequenceResult> rows = ReadResultsCsv(dir_ / "batch_lens" / "results.csv");
  const CameraRefit used = MapSnapshotView::Open(path("lens_refined")).camera_refit();
  ASSERT_EQ(rows.size(), 1u);
  ASSERT_TRUE(used.refined());
  ASSERT_TRUE(rows[0].camera_refit_k1.has_value());
  EXPECT_NEAR(*rows[0].camera_refit_k1, used.k1, 1e-5);
  run = RunApp(lens + path("lens_both") + " --keep-camera --camera-from " + path("lens_refined"));
  EXPECT_NE(run.exit_code, 0) << run.output;
  EXPECT_TRUE(Contains(run.output, "choose one camera")) << run.output;
  // A refined session saved before snapshots recorded the camera it was given (fx 0 there): its
  // keypoints cannot be moved into another camera, so the merge refuses it and says what to do.
  {
    LoadedSnapshot old = LoadMapSnapshot(path("lens_refined"));
    ASSERT_TRUE(old.metadata.camera_refit.refined());
    old.metadata.given_camera = PinholeCamera{};
    const SnapshotMapRef ref{old.maps.front().id, &old.maps.front().map};
    SaveMapSnapshot(path("lens_old"), {&ref, 1}, old.metadata);
  }
  const Result refused = RunApp("map merge " + path("lens_kept") + " " + path("lens_old") + " -o " + path("out_old"));
  EXPECT_EQ(refused.exit_code, 1) << refused.output;
  EXPECT_TRUE(Contains(refused.output, "cannot be re-expressed in another: run the later sessions with --camera-from " +
                                           path("lens_kept")))
      << refused.output;
  EXPECT_FALSE(fs::exists(path("out_old")));
}

void MapMergeCli::RefusesAnotherVocabulary() {
  ASSERT_TRUE(fs::exists(path("novocab"))) << setup_;
  Result r = RunApp("map merge " + path("room1") + " " + path("novocab") + " -o " + path("out_vocab"));
  EXPECT_NE(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "vocabulary")) << r.output;
  EXPECT_FALSE(fs::exists(path("out_vocab")));
  r = RunApp("map merge " + path("room1") + " " + path("room2") + " --vocabulary " + (dir_ / "none.fsvc").string() +
             " -o " + path("out_vocab"));
  EXPECT_NE(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "none.fsvc")) << r.output;
  EXPECT_FALSE(fs::exists(path("out_vocab")));
}

void MapMergeCli::RefusesToOverwriteAnInput() {
  const std::string before = ReadBytes(path("room1"));
  Result r = RunApp("map merge " + path("room1") + " " + path("room2") + " -o " + path("room1"));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_TRUE(Contains(r.output, "is an input")) << r.output;
  EXPECT_EQ(ReadBytes(path("room1")), before);
  r = RunApp("map merge " + path("room1") + " -o " + path("single"));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  r = RunApp("map merge " + path("room1") + " " + path("room2"));
  EXPECT_EQ(r.exit_code, 2) << r.output;
  EXPECT_TRUE(Contains(r.output, "-o OUT")) << r.output;
}

}  // namespace
}  // namespace flatslam
