// End-to-end checks of the flatslam command line: exit codes, messages, and the
// synth -> info -> eval chain a user runs.
#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>

#include <gtest/gtest.h>
#include <sys/wait.h>

#include "cli.h"
#include "test_data.h"

namespace flatslam {
namespace {

using testing::Contains;
using testing::RunApp;
using Result = testing::CliResult;

TEST(FlatslamCli, HelpAndUsageErrors) {
  Result r = RunApp("help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_TRUE(Contains(r.output, "synth")) << r.output;
  EXPECT_TRUE(Contains(r.output, "eval")) << r.output;
  r = RunApp("eval --help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_TRUE(Contains(r.output, "usage: flatslam eval")) << r.output;
  r = RunApp("");
  EXPECT_EQ(r.exit_code, 2);
  r = RunApp("fly");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "unknown command 'fly'")) << r.output;
  r = RunApp("synth --scene");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "--scene needs a value")) << r.output;
  r = RunApp("synth --scene moon");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "unknown synthetic scene 'moon'")) << r.output;
}

TEST(FlatslamCli, BadDatasetNamesWhatIsWrong) {
  const auto dir = testing::FreshTempDir("cli_bad");
  Result r = RunApp("info " + (dir / "nowhere").string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "nowhere")) << r.output;
  r = RunApp("info " + (testing::DatasetsDir() / "kitti" / "sequences" / "07").string() + " --sensor rgbd");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "error")) << r.output;
}

TEST(FlatslamCli, SynthWritesWhatInfoReadsAndEvalScores) {
  const auto dir = testing::FreshTempDir("cli_synth");
  const std::string out = (dir / "tum").string();
  Result r = RunApp("synth --scene room:width=320,height=240,duration=3 --sensor rgbd --out " + out + " --format tum");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  r = RunApp("info " + out + " --check");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "rgbd")) << r.output;
  EXPECT_TRUE(Contains(r.output, "60 poses")) << r.output;
  EXPECT_TRUE(Contains(r.output, "all 60 frames read")) << r.output;
  // Ground truth against itself: zero error, every pose paired.
  const std::string gt = out + "/groundtruth.txt";
  r = RunApp("eval " + gt + " " + gt + " --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "\"pairs\": 60") || Contains(r.output, "\"pairs\":60")) << r.output;
  // Writing into the same, now non-empty, folder is refused and changes nothing.
  r = RunApp("synth --scene room:duration=1 --out " + out + " --format kitti");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "refusing to overwrite")) << r.output;
  EXPECT_TRUE(std::filesystem::exists(out + "/rgb.txt"));
}

TEST(FlatslamCli, EvalReproducesPublishedAte) {
  const auto traj = testing::DatasetsDir() / "trajectories";
  Result r = RunApp("eval " + (traj / "fr2_desk_ORB.txt").string() + " " +
                    (traj / "fr2_desk_groundtruth.txt").string() + " --align se3 --json");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "2225")) << r.output;
  EXPECT_TRUE(Contains(r.output, "0.0081")) << r.output;
}

}  // namespace
}  // namespace flatslam
