// flatslam batch end to end: the table, the report, shards joined by --collect equal to the
// unsharded batch, failures and bad arguments.
#include <gtest/gtest.h>

#include <fstream>

#include "cli.h"
#include "report/results.h"
#include "test_data.h"

namespace flatslam {
namespace {

using testing::Contains;
using testing::RunApp;

// The cells that do not depend on timing or on the machine's load.
std::vector<std::vector<std::string>> StableCells(const std::vector<SequenceResult>& rows) {
  std::vector<std::vector<std::string>> out;
  for (SequenceResult r : rows) {
    r.wall_s = r.fps = r.cpu_ms_per_frame = r.peak_rss_mib = 0;
    out.push_back(ResultCells(r));
  }
  return out;
}

TEST(BatchCli, ShardsCollectedEqualTheWholeBatch) {
  const auto dir = testing::FreshTempDir("batch_cli_shards");
  {
    std::ofstream manifest(dir / "inputs.txt");
    manifest << "synth:room:duration=3 --name room\n"
                "synth:room:duration=3 --sensor rgbd --name room_rgbd\n"
                "synth:corridor:duration=3 --name corridor --set orb.features=800\n";
  }
  const std::string inputs = (dir / "inputs.txt").string() + " synth:room:duration=3,seed=2";
  auto r = RunApp("batch " + inputs + " --deterministic --quiet --out " + (dir / "all").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "| summary |")) << r.output;
  for (const char* file : {"results.csv", "results.json", "report.html"})
    EXPECT_TRUE(std::filesystem::exists(dir / "all" / file)) << file;
  for (int shard = 0; shard < 2; ++shard) {
    r = RunApp("batch " + inputs + " --deterministic --quiet --shard " + std::to_string(shard) + "/2 --out " +
               (dir / ("shard" + std::to_string(shard))).string());
    ASSERT_EQ(r.exit_code, 0) << r.output;
    EXPECT_TRUE(Contains(r.output, "2 sequences (shard " + std::to_string(shard) + "/2 of 4 inputs)")) << r.output;
  }
  r = RunApp("batch --collect " + (dir / "shard1").string() + " " + (dir / "shard0").string() + " --out " +
             (dir / "joined").string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "collected     4 sequences from 2 folders")) << r.output;
  const auto whole = ReadResultsCsv(dir / "all" / "results.csv");
  const auto joined = ReadResultsCsv(dir / "joined" / "results.csv");
  ASSERT_EQ(whole.size(), 4u);
  EXPECT_EQ(whole[1].name, "room_rgbd");
  EXPECT_EQ(whole[1].sensor, "rgbd");
  EXPECT_EQ(whole[3].name, "synth_room_duration=3_seed=2");
  for (const auto& row : whole) EXPECT_EQ(row.status, "ok") << row.name << ": " << row.error;
  EXPECT_EQ(StableCells(joined), StableCells(whole));
  EXPECT_TRUE(std::filesystem::exists(dir / "joined" / "report.html"));
  // The same shard twice is refused.
  r = RunApp("batch --collect " + (dir / "shard0").string() + " " + (dir / "shard0").string() + " --out " +
             (dir / "twice").string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "is also in")) << r.output;
}

TEST(BatchCli, AFailedSequenceIsReportedAndTheOthersFinish) {
  const auto dir = testing::FreshTempDir("batch_cli_failure");
  // A manifest's datasets are opened when their turn comes: a missing one fails alone.
  std::ofstream(dir / "m.txt") << "synth:room:duration=2\nmissing\n";
  const auto r = RunApp("batch " + (dir / "m.txt").string() + " --quiet --out " + (dir / "out").string());
  EXPECT_EQ(r.exit_code, 1) << r.output;
  EXPECT_TRUE(Contains(r.output, "failed        missing: ")) << r.output;
  const auto rows = ReadResultsCsv(dir / "out" / "results.csv");
  ASSERT_EQ(rows.size(), 2u);
  EXPECT_EQ(rows[0].status, "ok") << rows[0].error;
  EXPECT_EQ(rows[1].status, "failed");
}

TEST(BatchCli, BadArgumentsAndManifestsSayWhatIsWrong) {
  const auto dir = testing::FreshTempDir("batch_cli_errors");
  auto r = RunApp("batch synth:room --memory lots");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "--memory: cannot read 'lots'")) << r.output;
  r = RunApp("batch synth:room --shard 2/2");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "--shard: cannot read '2/2'")) << r.output;
  r = RunApp("batch");
  EXPECT_EQ(r.exit_code, 2);
  std::ofstream(dir / "m.yaml") << "- path: synth:room\n  speed: 3\n";
  r = RunApp("batch " + (dir / "m.yaml").string() + " --out " + (dir / "out").string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "m.yaml:2: unknown key 'speed'")) << r.output;
  r = RunApp("batch --collect " + dir.string() + " --out " + (dir / "c").string());
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "no results.csv")) << r.output;
}

// docs/batch: the Slurm job array, the Kubernetes indexed Job and the GNU parallel script each
// run their slices of a manifest, and the collected table holds every sequence once.
class ClusterExamples : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::FreshTempDir("batch_cli_examples");
    std::ofstream(dir_ / "inputs.txt") << "synth:room:duration=2 --name a\n"
                                          "synth:corridor:duration=2 --name b\n"
                                          "synth:room:duration=2 --sensor rgbd --name c\n";
  }
  // Joins the slices in `out` and checks the table.
  void ExpectCollected(const std::filesystem::path& out, const std::string& output) {
    SCOPED_TRACE(output);
    const auto r = RunApp("batch --collect " + out.string() + "/shard-* --out " + (out / "all").string());
    ASSERT_EQ(r.exit_code, 0) << r.output;
    const auto rows = ReadResultsCsv(out / "all" / "results.csv");
    ASSERT_EQ(rows.size(), 3u);
    for (size_t i = 0; i < 3; ++i) {
      EXPECT_EQ(rows[i].name, std::string(1, static_cast<char>('a' + i)));
      EXPECT_EQ(rows[i].input, i);
      EXPECT_EQ(rows[i].status, "ok") << rows[i].error;
    }
  }
  std::filesystem::path dir_;
  const std::filesystem::path docs_ = std::filesystem::path(FLATSLAM_SOURCE_DIR) / "docs" / "batch";
};

TEST_F(ClusterExamples, SlurmJobArray) {
  const auto out = dir_ / "slurm";
  std::string log;
  for (int task = 0; task < 2; ++task) {
    const auto r =
        testing::RunCommand("SLURM_ARRAY_TASK_ID=" + std::to_string(task) +
                            " SLURM_ARRAY_TASK_COUNT=2 SLURM_CPUS_PER_TASK=1 SLURM_MEM_PER_NODE=4096 INPUTS=" +
                            (dir_ / "inputs.txt").string() + " OUT=" + out.string() +
                            " FLATSLAM=" + testing::AppPath() + " bash " + (docs_ / "slurm.sbatch").string());
    ASSERT_EQ(r.exit_code, 0) << r.output;
    log += r.output;
  }
  ExpectCollected(out, log);
}

TEST_F(ClusterExamples, KubernetesIndexedJob) {
  const std::string yaml = testing::ReadBytes(docs_ / "kubernetes-job.yaml");
  ASSERT_TRUE(Contains(yaml, "completionMode: Indexed"));
  const size_t c = yaml.find("completions: ");
  ASSERT_NE(c, std::string::npos);
  const int completions = std::stoi(yaml.substr(c + 13));
  const size_t a = yaml.find("args: [\"");
  ASSERT_NE(a, std::string::npos);
  std::string command = yaml.substr(a + 8, yaml.find("\"]", a) - (a + 8));
  // The pod's command line, with this machine's executable, manifest and results folder.
  ASSERT_TRUE(Contains(command, "--shard $JOB_COMPLETION_INDEX/" + std::to_string(completions) + " ")) << command;
  auto replace = [&](const std::string& from, const std::string& to) {
    const size_t at = command.find(from);
    ASSERT_NE(at, std::string::npos) << from << " in " << command;
    command.replace(at, from.size(), to);
  };
  const auto out = dir_ / "kubernetes";
  replace("flatslam batch", testing::AppPath() + " batch");
  replace("/data/inputs.txt", (dir_ / "inputs.txt").string());
  replace("/results/", out.string() + "/");
  std::string log;
  // More pods than sequences: a slice may be empty, and still succeeds.
  for (int index = 0; index < completions; ++index) {
    const auto r = testing::RunCommand("JOB_COMPLETION_INDEX=" + std::to_string(index) + " sh -c '" + command + "'");
    ASSERT_EQ(r.exit_code, 0) << r.output;
    log += r.output;
  }
  ExpectCollected(out, log);
}

TEST_F(ClusterExamples, GnuParallel) {
  if (testing::RunCommand("command -v parallel").exit_code != 0) GTEST_SKIP() << "GNU parallel is not installed";
  const auto out = dir_ / "parallel";
  const auto r = testing::RunCommand("FLATSLAM=" + testing::AppPath() + " bash " + (docs_ / "parallel.sh").string() +
                                     " " + (dir_ / "inputs.txt").string() + " " + out.string() + " 2");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  ExpectCollected(out, r.output);
}

}  // namespace
}  // namespace flatslam
