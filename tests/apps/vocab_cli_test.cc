// End-to-end checks of `flatslam vocab`: train from a synthetic scene and an image folder, describe
// the file, and the usage and input errors.
#include <array>
#include <cstdio>
#include <filesystem>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/imgcodecs.hpp>
#include <sys/wait.h>

#include "io/synthetic.h"
#include "place/vocabulary.h"
#include "cli.h"
#include "test_data.h"

namespace flatslam {
namespace {

using testing::Contains;
using testing::RunApp;
using Result = testing::CliResult;

TEST(VocabCli, TrainThenInfo) {
  const auto dir = testing::FreshTempDir("vocab_cli");
  // An image folder: a few rendered frames written as PNG.
  const auto images = dir / "images";
  std::filesystem::create_directories(images);
  const auto dataset = OpenDataset("synth:corridor:sensor=mono,duration=2,fps=2");
  for (size_t i = 0; i < dataset->size(); ++i) {
    cv::imwrite((images / ("frame" + std::to_string(i) + ".png")).string(), dataset->read(i).left);
  }
  const auto out = dir / "small.fsvc";
  Result r = RunApp("vocab train --images synth:room:sensor=mono,duration=3,fps=3 " + images.string() + " --out " +
                    out.string() + " --branching 6 --levels 3 --features 300");
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "image folder")) << r.output;
  EXPECT_TRUE(Contains(r.output, "from 13 images")) << r.output;
  const Vocabulary v = Vocabulary::Load(out);
  EXPECT_EQ(v.branching(), 6);
  EXPECT_EQ(v.levels(), 3);
  EXPECT_GT(v.word_count(), 50u);
  EXPECT_EQ(v.training_images(), 13u);

  r = RunApp("vocab info " + out.string());
  ASSERT_EQ(r.exit_code, 0) << r.output;
  EXPECT_TRUE(Contains(r.output, "branching 6, levels 3")) << r.output;
  EXPECT_TRUE(Contains(r.output, std::to_string(v.word_count()) + " words")) << r.output;
  char checksum[32];
  std::snprintf(checksum, sizeof(checksum), "%016llx", static_cast<unsigned long long>(v.checksum()));
  EXPECT_TRUE(Contains(r.output, checksum)) << r.output;
  std::filesystem::remove_all(dir);
}

TEST(VocabCli, UsageAndInputErrors) {
  Result r = RunApp("vocab --help");
  EXPECT_EQ(r.exit_code, 0);
  EXPECT_TRUE(Contains(r.output, "usage: flatslam vocab train")) << r.output;
  r = RunApp("vocab");
  EXPECT_EQ(r.exit_code, 2);
  r = RunApp("vocab train --out /tmp/x.fsvc");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "--images")) << r.output;
  r = RunApp("vocab train --images synth:room --out /tmp/x.fsvc --branching 1");
  EXPECT_EQ(r.exit_code, 2);
  r = RunApp("vocab compress x");
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(Contains(r.output, "unknown vocab action 'compress'")) << r.output;
  r = RunApp("vocab info /nonexistent/v.fsvc");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "/nonexistent/v.fsvc")) << r.output;
  EXPECT_TRUE(Contains(r.output, "cannot open")) << r.output;
  r = RunApp("vocab train --images /nonexistent/folder --out /tmp/x.fsvc");
  EXPECT_EQ(r.exit_code, 1);
  EXPECT_TRUE(Contains(r.output, "/nonexistent/folder")) << r.output;
}

}  // namespace
}  // namespace flatslam
