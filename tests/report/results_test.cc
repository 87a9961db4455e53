// The results table: CSV round trip, JSON, the summary row and errors naming line and column.
#include "report/results.h"

#include <gtest/gtest.h>

#include <fstream>

#include "expect_error.h"
#include "test_data.h"

namespace flatslam {
namespace {

using testing::ReadBytes;

std::vector<SequenceResult> Rows() {
  SequenceResult a;
  a.name = "kitti_06";
  a.input = 0;
  a.dataset = "/data/kitti/sequences/06";
  a.sensor = "stereo";
  a.status = "ok";
  a.frames = 201;
  a.tracked = 201;
  a.keyframes = 40;
  a.ate_se3_m = 0.0347;
  a.ate_sim3_m = 0.0331;
  a.scale = 1.0012;
  a.rpe_m = 0.02;
  a.rpe_deg = 0.1;
  a.path_m = 120.5;
  a.kitti_t_rel_pct = 1.25;
  a.kitti_r_rel_deg_per_100m = 0.5;
  a.wall_s = 5.5;
  a.fps = 36.5;
  a.cpu_ms_per_frame = 48.25;
  a.peak_rss_mib = 300;
  SequenceResult b;
  b.name = "mine";
  b.input = 2;
  b.dataset = "/data/odd, \"quoted\"\nname";
  b.sensor = "mono";
  b.status = "failed";
  b.error = "frame 3: cannot read, it says \"truncated\"";
  b.frames = 9;
  b.lost = 4;
  b.segments = 2;
  b.fps = 10;
  b.peak_rss_mib = 100;
  SequenceResult c = a;
  c.name = "synth";
  c.input = 1;
  c.ate_se3_m = 0.01;
  c.ate_sim3_m.reset();
  c.frames = 100;
  c.fps = 50;
  c.camera_refit_k1 = 0.0191;  // a monocular run that started over with a refined camera
  c.camera_refit_focal_scale = 1.0061;
  return {a, b, c};
}

TEST(ResultsTable, CsvRoundTripKeepsEveryCell) {
  const auto dir = testing::FreshTempDir("results_csv");
  const auto rows = Rows();
  WriteResultsCsv(dir / "results.csv", rows);
  const auto back = ReadResultsCsv(dir / "results.csv");
  ASSERT_EQ(back.size(), rows.size());
  for (size_t i = 0; i < rows.size(); ++i) EXPECT_EQ(ResultCells(back[i]), ResultCells(rows[i])) << i;
  EXPECT_EQ(back[1].dataset, rows[1].dataset);
  EXPECT_FALSE(back[1].ate_se3_m.has_value());
  EXPECT_FALSE(back[2].ate_sim3_m.has_value());
  EXPECT_FALSE(back[0].camera_refit_k1.has_value());
  ASSERT_TRUE(back[2].camera_refit_k1.has_value());
  EXPECT_EQ(*back[2].camera_refit_k1, 0.0191);
  EXPECT_EQ(*back[2].camera_refit_focal_scale, 1.0061);
}

TEST(ResultsTable, SummaryAddsCountsAndTakesMediansOfKnownMetrics) {
  const SequenceResult s = SummarizeResults(Rows());
  EXPECT_EQ(s.name, "summary");
  EXPECT_EQ(s.status, "2 of 3 ok");
  EXPECT_EQ(s.frames, 310u);
  EXPECT_EQ(s.lost, 4u);
  EXPECT_EQ(s.segments, 2u);
  EXPECT_EQ(s.keyframes, 80u);
  EXPECT_DOUBLE_EQ(s.wall_s, 11.0);
  ASSERT_TRUE(s.ate_se3_m.has_value());
  EXPECT_DOUBLE_EQ(*s.ate_se3_m, 0.5 * (0.0347 + 0.01));  // the failed row has none
  ASSERT_TRUE(s.ate_sim3_m.has_value());
  EXPECT_DOUBLE_EQ(*s.ate_sim3_m, 0.0331);  // the only one known
  EXPECT_DOUBLE_EQ(s.fps, 36.5);            // median of 36.5, 10, 50
  EXPECT_FALSE(SummarizeResults({}).ate_se3_m.has_value());
}

TEST(ResultsTable, JsonHasNumbersNullsAndEscapedText) {
  const auto dir = testing::FreshTempDir("results_json");
  WriteResultsJson(dir / "results.json", Rows());
  const std::string json = ReadBytes(dir / "results.json");
  EXPECT_NE(json.find("\"ate_se3_m\": 0.0347"), std::string::npos) << json;
  EXPECT_NE(json.find("\"ate_se3_m\": null"), std::string::npos) << json;
  EXPECT_NE(json.find("\"frames\": 201"), std::string::npos) << json;
  EXPECT_NE(json.find("\\\"truncated\\\""), std::string::npos) << json;
  EXPECT_NE(json.find("odd, \\\"quoted\\\"\\u000aname"), std::string::npos) << json;
  EXPECT_NE(json.find("\"summary\": {\"sequence\": \"summary\""), std::string::npos) << json;
}

TEST(ResultsTable, MarkdownHasARowPerSequenceAndTheSummary) {
  const std::string md = ResultsMarkdown(Rows());
  EXPECT_EQ(std::count(md.begin(), md.end(), '\n'), 2 + 3 + 1);
  EXPECT_NE(md.find("| kitti_06 | stereo | ok | 201 |"), std::string::npos) << md;
  EXPECT_NE(md.find("| summary |"), std::string::npos) << md;
}

TEST(ResultsTable, ReadErrorsNameLineAndColumn) {
  const auto dir = testing::FreshTempDir("results_errors");
  std::ofstream(dir / "a.csv") << "sequence,frames\nx,12\ny,twelve\n";
  testing::ExpectErrorMentions([&] { (void)ReadResultsCsv(dir / "a.csv"); }, {"a.csv:3", "'frames'", "twelve"});
  std::ofstream(dir / "b.csv") << "sequence,frames,colour\n";
  testing::ExpectErrorMentions([&] { (void)ReadResultsCsv(dir / "b.csv"); }, {"b.csv:1", "unknown column 'colour'"});
  std::ofstream(dir / "c.csv") << "sequence,frames\nx,1,2\n";
  testing::ExpectErrorMentions([&] { (void)ReadResultsCsv(dir / "c.csv"); }, {"c.csv:2", "3 cells, expected 2"});
  std::ofstream(dir / "d.csv") << "frames\n1\n";
  testing::ExpectErrorMentions([&] { (void)ReadResultsCsv(dir / "d.csv"); }, {"d.csv:1", "no 'sequence' column"});
  std::ofstream(dir / "e.csv") << "sequence,frames\n\"open,1\n";
  testing::ExpectErrorMentions([&] { (void)ReadResultsCsv(dir / "e.csv"); }, {"e.csv:2", "not closed"});
  // A table of fewer columns still reads (columns go by name).
  std::ofstream(dir / "f.csv") << "frames,sequence\n5,z\n";
  const auto rows = ReadResultsCsv(dir / "f.csv");
  ASSERT_EQ(rows.size(), 1u);
  EXPECT_EQ(rows[0].name, "z");
  EXPECT_EQ(rows[0].frames, 5u);
}

}  // namespace
}  // namespace flatslam
