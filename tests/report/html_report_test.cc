#include "report/html_report.h"

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <fstream>
#include <random>
#include <regex>
#include <string>

#include <gtest/gtest.h>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>

#include "core/error.h"
#include "expect_error.h"
#include "test_data.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

using testing::ReadBytes;

namespace fs = std::filesystem;

constexpr const char* kChromium = "/usr/bin/chromium";
// Line colours chosen in src/report/html_report.cc (ground truth, estimate, frames/s).
const cv::Vec3b kGroundTruthBgr(81, 166, 0);
const cv::Vec3b kEstimateBgr(126, 0, 230);
const cv::Vec3b kFpsBgr(216, 100, 28);
// The batch below: 4 plots for the sequence with ground truth and stats, 3 without ground truth
// (top view, frames/s, keyframes), none for the failed one.
constexpr int kExpectedCharts = 7;

fs::path TempDir() {
  static const fs::path dir = testing::FreshTempDir("html_report");
  return dir;
}

size_t Count(const std::string& text, const std::string& part) {
  size_t n = 0;
  for (size_t at = text.find(part); at != std::string::npos; at = text.find(part, at + 1)) ++n;
  return n;
}

// A loop in the x-z plane of a camera frame (y down, as KITTI), 10 Hz, a little vertical motion.
Trajectory LoopGroundTruth(size_t n) {
  Trajectory gt;
  for (size_t i = 0; i < n; ++i) {
    const double a = 2 * M_PI * static_cast<double>(i) / static_cast<double>(n);
    TimedPose pose;
    pose.t_ns = 1'000'000'000 + static_cast<int64_t>(i) * 100'000'000;
    pose.T_world_cam.linear() = Eigen::AngleAxisd(-a, Eigen::Vector3d::UnitY()).toRotationMatrix();
    pose.T_world_cam.translation() = Eigen::Vector3d(40 * std::sin(a), 0.3 * std::sin(3 * a), 25 * (1 - std::cos(a)));
    gt.push_back(pose);
  }
  return gt;
}

// The ground truth seen by a monocular run: another frame, another scale, a drift that grows and
// shrinks along the loop (so the two lines are apart in the top view), and noise.
Trajectory MonoEstimate(const Trajectory& gt, uint32_t seed) {
  std::mt19937 rng(seed);
  std::normal_distribution<double> noise(0, 0.02);
  Eigen::Isometry3d T_est_world = Eigen::Isometry3d::Identity();
  T_est_world.linear() = Eigen::AngleAxisd(0.5, Eigen::Vector3d(0.2, 1, 0.1).normalized()).toRotationMatrix();
  T_est_world.translation() = Eigen::Vector3d(3, -1, 2);
  const double scale = 0.4;
  Trajectory est;
  for (size_t i = 0; i < gt.size(); ++i) {
    const TimedPose& g = gt[i];
    const double drift = 3.0 * std::sin(M_PI * static_cast<double>(i) / static_cast<double>(gt.size()));
    TimedPose pose = g;
    pose.T_world_cam = T_est_world * g.T_world_cam;
    const Eigen::Vector3d p_gt = g.T_world_cam.translation() + Eigen::Vector3d(drift, 0, -drift);
    pose.T_world_cam.translation() = T_est_world.linear() * (scale * p_gt) + T_est_world.translation() +
                                     Eigen::Vector3d(noise(rng), noise(rng), noise(rng));
    est.push_back(pose);
  }
  return est;
}

// stats.csv as `flatslam run` writes it: keyframes every 8 frames, some culled, a few lost and
// skipped frames, timings that slow down half way.
void WriteStats(const fs::path& path, const Trajectory& frames) {
  std::ofstream out(path);
  out << "frame,t_ns,state,keyframe,reinitialized,relocalized,features,stereo_points,matches,inliers,extract_ms,"
         "track_ms,rss_mib,heap_mib,map_keyframes,map_points\n";
  size_t keyframes = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    const bool skipped = i % 97 == 50;
    const bool keyframe = !skipped && i % 8 == 0;
    keyframes += keyframe;
    const double extract_ms = skipped ? 0 : 6 + (i > frames.size() / 2 ? 6 : 0) + 0.5 * std::sin(0.3 * i);
    const double track_ms = skipped ? 0 : 9 + 0.7 * std::cos(0.2 * i);
    // Not initialized at the start, and after a loss while a new map segment starts (lost).
    const char* state = skipped ? "skipped" : i == 0 || i % 131 == 9 ? "not_initialized" : i % 131 == 7 ? "lost" : "ok";
    out << i << ',' << frames[i].t_ns << ',' << state << ',' << keyframe << ",0,0,1500,0,400,300," << extract_ms << ','
        << track_ms << ",120,80," << (keyframes - keyframes / 5) << ',' << 40 * i << '\n';
  }
  out << "600,17000";  // the cut last line of a killed run
}

// A batch of three sequences: monocular with ground truth, stereo without ground truth, and a
// failed one whose folder holds nothing. Written once for all tests.
const fs::path& Report() {
  static const fs::path html = [] {
    const fs::path root = TempDir() / "batch";
    const Trajectory gt = LoopGroundTruth(6000);

    ReportSequence mono;
    mono.dir = root / "mono_loop";
    fs::create_directories(mono.dir);
    WriteTum(mono.dir / "groundtruth.tum", gt);
    WriteTum(mono.dir / "trajectory.tum", MonoEstimate(gt, 7));
    WriteStats(mono.dir / "stats.csv", gt);
    mono.result.name = "loop <&> mono";
    mono.result.dataset = "synth:loop";
    mono.result.sensor = "mono";
    mono.result.status = "ok";
    mono.result.frames = 6000;
    mono.result.tracked = 5950;
    mono.result.keyframes = 740;
    mono.result.ate_sim3_m = 0.034;
    mono.result.scale = 2.5;
    mono.result.fps = 95;

    ReportSequence stereo;
    stereo.dir = root / "stereo_no_gt";
    fs::create_directories(stereo.dir);
    Trajectory line = LoopGroundTruth(300);
    for (TimedPose& pose : line) pose.T_world_cam.translation().z() *= 0.3;
    WriteTum(stereo.dir / "trajectory.tum", line);
    WriteStats(stereo.dir / "stats.csv", line);
    stereo.result.name = "stereo_no_gt";
    stereo.result.dataset = "/data/stereo";
    stereo.result.sensor = "stereo";
    stereo.result.status = "ok";
    stereo.result.frames = 300;
    stereo.result.fps = 60;

    ReportSequence failed;
    failed.dir = root / "broken";  // never created
    failed.result.name = "broken";
    failed.result.dataset = "/data/broken";
    failed.result.sensor = "stereo";
    failed.result.status = "failed";
    failed.result.error = "cannot open /data/broken: <missing> & gone";

    const fs::path path = root / "report.html";
    WriteHtmlReport(path, "Batch <test> & report", {mono, stereo, failed});
    return path;
  }();
  return html;
}

TEST(HtmlReport, IsSelfContained) {
  const std::string page = ReadBytes(Report());
  ASSERT_FALSE(page.empty());
  // Nothing is loaded from elsewhere: no external script, style, image or frame.
  for (const char* load : {"src=\"http", "src='http", "href=\"http", "href='http", "url(http", "url(\"http", "@import",
                           "<script src", "<link"})
    EXPECT_EQ(page.find(load), std::string::npos) << load;
  // Chart.js itself is in the page (its licence header and code).
  const std::string chart_js = ReadBytes("/usr/share/javascript/chart.js/chart.min.js");
  ASSERT_GT(chart_js.size(), 1000u);
  EXPECT_NE(page.find(chart_js.substr(0, 1000)), std::string::npos);
  EXPECT_NE(page.find("Chart.js v3.9.1"), std::string::npos);
  EXPECT_GT(page.size(), chart_js.size());
  // 6000 poses would take over 600 KB of JSON: the plots get at most 2000 points per path.
  EXPECT_LT(page.size(), chart_js.size() + 400'000);
}

// Frames without a pose after the first count as lost, whatever state they were in.
TEST(HtmlReport, CountsFramesWaitingForANewSegmentAsLost) {
  const std::string page = ReadBytes(Report());
  size_t lost = 0;
  for (size_t i = 1; i < 300; ++i) lost += i % 97 != 50 && (i % 131 == 7 || i % 131 == 9);
  EXPECT_NE(page.find("stats.csv: 300 frames, " + std::to_string(lost) + " lost, 3 skipped."), std::string::npos)
      << lost;
}

TEST(HtmlReport, NamesEverySequenceAndEscapesText) {
  const std::string page = ReadBytes(Report());
  EXPECT_NE(page.find("loop &lt;&amp;&gt; mono"), std::string::npos);
  EXPECT_EQ(page.find("loop <&> mono"), std::string::npos);
  EXPECT_NE(page.find("<title>Batch &lt;test&gt; &amp; report</title>"), std::string::npos);
  EXPECT_NE(page.find("stereo_no_gt"), std::string::npos);
  EXPECT_NE(page.find(">broken<"), std::string::npos);
  EXPECT_NE(page.find("cannot open /data/broken: &lt;missing&gt; &amp; gone"), std::string::npos);
  EXPECT_EQ(page.find("<missing>"), std::string::npos);
  // The table links each row to its section, marks the failure and ends with the summary row.
  EXPECT_NE(page.find("<a href=\"#seq-1-loopmono\">"), std::string::npos);
  EXPECT_NE(page.find("id=\"seq-1-loopmono\""), std::string::npos);
  EXPECT_NE(page.find("<tr class=\"failed\">"), std::string::npos);
  EXPECT_NE(page.find("<td>summary</td>"), std::string::npos);
  // What each sequence lacks is said.
  EXPECT_NE(page.find("No ground truth (no groundtruth.tum): the estimate is shown alone"), std::string::npos);
  EXPECT_NE(page.find("trajectory.tum is missing"), std::string::npos);
  EXPECT_NE(page.find("stats.csv is missing"), std::string::npos);
  EXPECT_NE(page.find("1 line(s) could not be read"), std::string::npos);  // the cut last line
  // The monocular estimate is aligned by Sim(3) and its scale found (the estimate is 0.4 x).
  std::smatch scale;
  ASSERT_TRUE(std::regex_search(page, scale, std::regex("by Sim\\(3\\) \\(scale ([0-9.]+)\\)")));
  EXPECT_NEAR(std::stod(scale[1]), 2.5, 0.1);
}

TEST(HtmlReport, MissingChartJsNamesTheFileAndPackage) {
  const fs::path html = TempDir() / "no_chartjs.html";
  ASSERT_EQ(::setenv("FLATSLAM_CHARTJS", "/nonexistent/chart.min.js", 1), 0);
  testing::ExpectErrorMentions([&] { WriteHtmlReport(html, "t", {}); },
                               {"/nonexistent/chart.min.js", "apt-get install libjs-chart.js"});
  ::unsetenv("FLATSLAM_CHARTJS");
  EXPECT_FALSE(fs::exists(html));
}

TEST(HtmlReport, ScriptEndInChartJsCannotEndItsElement) {
  const fs::path fake = TempDir() / "fake_chart.js";
  std::ofstream(fake) << "var Chart = function () {}; var s = '</SCRIPT><!-- x';\n";
  const fs::path html = TempDir() / "fake.html";
  ASSERT_EQ(::setenv("FLATSLAM_CHARTJS", fake.c_str(), 1), 0);
  WriteHtmlReport(html, "fake", {});
  ::unsetenv("FLATSLAM_CHARTJS");
  const std::string page = ReadBytes(html);
  EXPECT_NE(page.find("var s = '<\\/SCRIPT><\\!-- x';"), std::string::npos);
  EXPECT_EQ(Count(page, "<script>"), Count(page, "</script>"));
  EXPECT_EQ(page.find("<!--"), std::string::npos);
}

// Runs chromium headless on the page with `arguments`; returns its standard output (stderr, where
// chromium prints noise, is dropped).
// Each run gets its own profile: a browser process left over from the last run (timeout kills only
// the first process) would otherwise hold the profile's lock, and the next run hand its page to it
// and draw nothing.
std::string RunChromium(const std::string& arguments, const fs::path& page) {
  static int runs = 0;
  const fs::path profile = TempDir() / ("chromium_profile_" + std::to_string(runs++));
  fs::create_directories(profile);
  const std::string command = std::string("timeout -k 5 60 ") + kChromium +
                              " --headless=new --no-sandbox --disable-gpu --no-first-run --hide-scrollbars"
                              " --user-data-dir='" +
                              profile.string() +
                              "' --run-all-compositor-stages-before-draw --virtual-time-budget=5000 " + arguments +
                              " 'file://" + page.string() + "' 2>/dev/null";
  std::FILE* pipe = ::popen(command.c_str(), "r");
  if (pipe == nullptr) return "";
  std::string out;
  char buffer[4096];
  for (size_t n; (n = std::fread(buffer, 1, sizeof(buffer), pipe)) > 0;) out.append(buffer, n);
  ::pclose(pipe);
  return out;
}

// Pixels within `tolerance` of `colour` on every channel.
int CountColour(const cv::Mat& image, const cv::Vec3b& colour, int tolerance = 40) {
  int count = 0;
  for (int r = 0; r < image.rows; ++r)
    for (int c = 0; c < image.cols; ++c) {
      const cv::Vec3b& p = image.at<cv::Vec3b>(r, c);
      count += std::abs(p[0] - colour[0]) <= tolerance && std::abs(p[1] - colour[1]) <= tolerance &&
               std::abs(p[2] - colour[2]) <= tolerance;
    }
  return count;
}

TEST(HtmlReport, DrawsEveryPlotInABrowser) {
  if (!fs::exists(kChromium)) GTEST_SKIP() << kChromium << " is not installed";
  const fs::path page = Report();

  // The page records how many charts it drew and any script error on <body>.
  const std::string dom = RunChromium("--dump-dom", page);
  ASSERT_FALSE(dom.empty()) << "chromium printed no DOM";
  std::smatch match;
  const std::string body = dom.substr(0, dom.find('>', dom.find("<body")) + 1);
  ASSERT_TRUE(std::regex_search(body, match, std::regex("data-charts=\"([0-9]+)\""))) << body;
  EXPECT_EQ(std::stoi(match[1]), kExpectedCharts);
  EXPECT_EQ(body.find("data-errors"), std::string::npos) << body;

  // The lines are drawn: the screenshot holds many pixels of each line's colour.
  const fs::path png = TempDir() / "report.png";
  // Headless chromium on a loaded machine now and then never writes its screenshot before the
  // timeout (the DOM above shows the page itself works): one more try before failing.
  cv::Mat image;
  for (int attempt = 0; attempt < 2 && image.empty(); ++attempt) {
    (void)RunChromium("--screenshot='" + png.string() + "' --window-size=1400,3000", page);
    if (fs::exists(png)) image = cv::imread(png.string(), cv::IMREAD_COLOR);
  }
  ASSERT_FALSE(image.empty()) << "no screenshot at " << png;
  EXPECT_EQ(image.cols, 1400);
  EXPECT_GT(CountColour(image, kGroundTruthBgr), 500) << "ground-truth line";
  EXPECT_GT(CountColour(image, kEstimateBgr), 1000) << "estimate lines";
  EXPECT_GT(CountColour(image, kFpsBgr), 500) << "frames/s lines";
  // FLATSLAM_KEEP_REPORT=DIR keeps the page and its screenshot for a look (the temp dir is removed).
  if (const char* keep = std::getenv("FLATSLAM_KEEP_REPORT")) {
    fs::create_directories(keep);
    fs::copy_file(page, fs::path(keep) / "report.html", fs::copy_options::overwrite_existing);
    fs::copy_file(png, fs::path(keep) / "report.png", fs::copy_options::overwrite_existing);
  }
}

}  // namespace
}  // namespace flatslam
