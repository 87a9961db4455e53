// report.html: one file holding its styles, Chart.js, the data and the script that draws it, so
// that it opens offline and can be archived or mailed as is. The C++ side reads the sequence
// folders and turns them into plot specifications (JSON); a small script on the page turns those
// into Chart.js charts.
#include "report/html_report.h"

#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <deque>
#include <fstream>
#include <iterator>
#include <optional>
#include <string_view>
#include <system_error>

#include <Eigen/Core>

#include "core/atomic_write.h"
#include "core/error.h"
#include "core/text.h"
#include "trajectory/metrics.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

// At most this many points per plotted path or time series: a report over many long sequences
// stays a few hundred KB per sequence, and the plots cannot show more points than pixels anyway.
constexpr size_t kMaxPathPoints = 2000;
constexpr size_t kMaxSeriesPoints = 1000;
// Processed frames averaged for one point of the frames/s curve.
constexpr size_t kFpsWindowFrames = 30;
// Below this ground-truth path length (m) the error is plotted over time instead of distance: a
// (nearly) static sequence would put every error at distance 0.
constexpr double kMinPathForDistanceAxis_m = 0.5;

// Line colours: distinct from each other and from every other colour of the page, so that a
// screenshot shows which line is which (tests/report/html_report_test.cc looks for the ground
// truth, estimate and frames/s colours in a screenshot).
constexpr const char* kGroundTruthColour = "#00a651";       // rgb(0, 166, 81)
constexpr const char* kEstimateColour = "#e6007e";          // rgb(230, 0, 126)
constexpr const char* kStartColour = "#222222";             // marker at the first pose
constexpr const char* kErrorColour = "#f08c00";             // position error
constexpr const char* kFpsColour = "#1c64d8";               // smoothed frames/s
constexpr const char* kWallFpsColour = "#8a8f98";           // the run's mean wall-clock frames/s
constexpr const char* kMapKeyframesColour = "#7b3fc4";      // keyframes in the map
constexpr const char* kCreatedKeyframesColour = "#0a9fbf";  // keyframes created so far

// ---- Text escaping ----

// Text for HTML element content and attribute values.
std::string HtmlEscape(std::string_view text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      case '\'':
        out += "&#39;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

// A JSON number with 6 significant digits (1 mm at 1 km), null when not finite.
std::string JsonNumber(double value) {
  if (!std::isfinite(value)) return "null";
  char text[32];
  std::snprintf(text, sizeof(text), "%.6g", value);
  return text;
}

// Code inlined into a <script> element: the HTML parser ends the element at "</script" and
// changes state at "<!--", whatever the JavaScript around them; "<\/" and "<\!" mean the same
// inside JavaScript strings, regular expressions and comments, where they can occur.
std::string InlineScript(std::string code) {
  std::string out;
  out.reserve(code.size() + 16);
  for (size_t i = 0; i < code.size(); ++i) {
    if (code[i] == '<' && i + 1 < code.size()) {
      const std::string_view rest(code.data() + i + 1, std::min<size_t>(7, code.size() - i - 1));
      std::string lower(rest);
      std::transform(lower.begin(), lower.end(), lower.begin(), [](unsigned char c) { return std::tolower(c); });
      if (lower.rfind("/script", 0) == 0) {
        out += "<\\/";
        ++i;  // the '/' is written above
        continue;
      }
      if (lower.rfind("!--", 0) == 0) {
        out += "<\\!";
        ++i;
        continue;
      }
    }
    out += code[i];
  }
  return out;
}

bool IsNumber(const std::string& text) {
  if (text.empty()) return false;
  char* end = nullptr;
  (void)std::strtod(text.c_str(), &end);
  return end == text.c_str() + text.size();
}

// An id usable in URLs and CSS selectors: the sequence's index (names are unique, but may hold any
// character) and its name's letters and digits for readable links.
std::string AnchorId(size_t index, const std::string& name) {
  std::string id = "seq-" + std::to_string(index + 1) + "-";
  for (char c : name)
    if (std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_') id += c;
  return id;
}

// ---- Chart.js ----

// Chart.js as shipped by Debian; FLATSLAM_CHARTJS overrides the path compiled in.
std::string ReadChartJs() {
  const char* env = std::getenv("FLATSLAM_CHARTJS");
  const fs::path path = (env != nullptr && *env != '\0') ? fs::path(env) : fs::path(FLATSLAM_CHARTJS_PATH);
  const char* hint =
      ": cannot read Chart.js, which the HTML report inlines; install it with `apt-get install libjs-chart.js` or "
      "set FLATSLAM_CHARTJS to its path";
  std::error_code ec;
  FLATSLAM_CHECK(fs::is_regular_file(path, ec), path.string(), hint);
  std::ifstream in(path, std::ios::binary);
  FLATSLAM_CHECK(in.good(), path.string(), hint);
  std::string code((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  FLATSLAM_CHECK(!in.bad() && !code.empty(), path.string(), hint);
  return code;
}

// ---- Plot specifications (drawn by the page's script) ----

using Point = Eigen::Vector2d;

struct Series {
  std::string label;
  const char* colour = kEstimateColour;
  std::vector<Point> points;
  bool line = true;      // joined by a line; false: markers only
  bool dashed = false;   // for reference lines
  double marker_px = 0;  // radius of the point markers
};

struct Plot {
  std::string canvas;  // id of its <canvas>
  std::string title, x_label, y_label;
  std::vector<Series> series;
  bool equal_scale = false;  // top view: a metre is as long on both axes
  bool y_from_zero = false;
};

std::string PlotJson(const Plot& plot) {
  std::string out = "{\"canvas\":" + JsonString(plot.canvas) + ",\"title\":" + JsonString(plot.title) +
                    ",\"x\":" + JsonString(plot.x_label) + ",\"y\":" + JsonString(plot.y_label) +
                    ",\"equal\":" + (plot.equal_scale ? "true" : "false") +
                    ",\"zero\":" + (plot.y_from_zero ? "true" : "false") + ",\"series\":[";
  for (size_t s = 0; s < plot.series.size(); ++s) {
    const Series& series = plot.series[s];
    out += s ? ",{" : "{";
    out += "\"label\":" + JsonString(series.label) + ",\"colour\":" + JsonString(series.colour) +
           ",\"line\":" + (series.line ? "true" : "false") + ",\"dashed\":" + (series.dashed ? "true" : "false") +
           ",\"marker\":" + JsonNumber(series.marker_px) + ",\"points\":[";
    for (size_t i = 0; i < series.points.size(); ++i) {
      if (i) out += ',';
      out += '[' + JsonNumber(series.points[i].x()) + ',' + JsonNumber(series.points[i].y()) + ']';
    }
    out += "]}";
  }
  return out + "]}";
}

// Every k-th point and the last, at most `max_points`: the shape of a path survives.
std::vector<Point> Thin(const std::vector<Point>& points, size_t max_points) {
  if (points.size() <= max_points) return points;
  const size_t step = (points.size() + max_points - 2) / (max_points - 1);
  std::vector<Point> out;
  size_t last = 0;
  for (size_t i = 0; i < points.size(); i += step) {
    out.push_back(points[i]);
    last = i;
  }
  if (last != points.size() - 1) out.push_back(points.back());
  return out;
}

// Per run of consecutive points the one with the largest y, at most `max_points`: error peaks stay
// visible, where taking every k-th point would drop most of them.
std::vector<Point> ThinKeepingPeaks(const std::vector<Point>& points, size_t max_points) {
  if (points.size() <= max_points) return points;
  const size_t step = (points.size() + max_points - 1) / max_points;
  std::vector<Point> out;
  for (size_t begin = 0; begin < points.size(); begin += step) {
    const auto end = points.begin() + static_cast<std::ptrdiff_t>(std::min(begin + step, points.size()));
    out.push_back(*std::max_element(points.begin() + static_cast<std::ptrdiff_t>(begin), end,
                                    [](const Point& a, const Point& b) { return a.y() < b.y(); }));
  }
  return out;
}

// ---- Sequence folder contents ----

// One line of stats.csv, the columns the plots use.
struct FrameRow {
  int64_t t_ns = 0;
  std::string state;  // ok, lost, not_initialized, ... or skipped (unreadable frame)
  bool keyframe = false;
  double work_ms = 0;  // extract_ms + track_ms
  double map_keyframes = 0;
};

std::vector<std::string> SplitCommas(const std::string& line) {
  std::vector<std::string> cells(1);
  for (char c : line) {
    if (c == ',')
      cells.emplace_back();
    else if (c != '\r')
      cells.back() += c;
  }
  return cells;
}

bool ParseDouble(const std::string& text, double* value) {
  if (text.empty()) return false;
  char* end = nullptr;
  *value = std::strtod(text.c_str(), &end);
  return end == text.c_str() + text.size();
}

bool ParseInt(const std::string& text, int64_t* value) {
  if (text.empty()) return false;
  char* end = nullptr;
  *value = std::strtoll(text.c_str(), &end, 10);
  return end == text.c_str() + text.size();
}

// The rows of stats.csv, or nothing with a note saying why. Lines that do not parse (the last line
// of a killed run may be cut) are skipped and counted in a note.
std::optional<std::vector<FrameRow>> ReadStats(const fs::path& dir, std::vector<std::string>* notes) {
  const fs::path path = dir / "stats.csv";
  std::error_code ec;
  if (!fs::exists(path, ec)) {
    notes->push_back("No per-frame statistics: stats.csv is missing from " + dir.string() +
                     ", so there are no frames/s and keyframe plots.");
    return std::nullopt;
  }
  std::ifstream in(path);
  std::string line;
  if (!in || !std::getline(in, line)) {
    notes->push_back("stats.csv in " + dir.string() + " cannot be read or is empty.");
    return std::nullopt;
  }
  const std::vector<std::string> header = SplitCommas(line);
  const auto column = [&](const char* name) -> std::optional<size_t> {
    const auto it = std::find(header.begin(), header.end(), name);
    if (it == header.end()) return std::nullopt;
    return static_cast<size_t>(it - header.begin());
  };
  const std::array<const char*, 6> names = {"t_ns", "state", "keyframe", "extract_ms", "track_ms", "map_keyframes"};
  std::array<size_t, 6> index{};
  for (size_t i = 0; i < names.size(); ++i) {
    const std::optional<size_t> found = column(names[i]);
    if (!found) {
      notes->push_back(std::string("stats.csv in ") + dir.string() + " has no column \"" + names[i] +
                       "\": no frames/s and keyframe plots.");
      return std::nullopt;
    }
    index[i] = *found;
  }
  std::vector<FrameRow> rows;
  size_t bad_lines = 0;
  while (std::getline(in, line)) {
    if (line.empty() || line == "\r") continue;
    const std::vector<std::string> cells = SplitCommas(line);
    FrameRow row;
    int64_t keyframe = 0;
    double extract_ms = 0, track_ms = 0;
    const bool ok = cells.size() == header.size() && ParseInt(cells[index[0]], &row.t_ns) &&
                    ParseInt(cells[index[2]], &keyframe) && ParseDouble(cells[index[3]], &extract_ms) &&
                    ParseDouble(cells[index[4]], &track_ms) && ParseDouble(cells[index[5]], &row.map_keyframes);
    if (!ok) {
      ++bad_lines;
      continue;
    }
    row.state = cells[index[1]];
    row.keyframe = keyframe != 0;
    row.work_ms = extract_ms + track_ms;
    rows.push_back(std::move(row));
  }
  if (bad_lines > 0)
    notes->push_back("stats.csv: " + std::to_string(bad_lines) + " line(s) could not be read and are left out.");
  return rows;
}

// The poses of a TUM file of the sequence folder, or nothing (with a note when it exists but cannot
// be read; the caller says what a missing file means).
std::optional<Trajectory> ReadPoses(const fs::path& path, std::vector<std::string>* notes) {
  std::error_code ec;
  if (!fs::exists(path, ec)) return std::nullopt;
  try {
    return ReadTum(path);
  } catch (const std::exception& e) {
    notes->push_back(path.filename().string() + " cannot be read: " + e.what());
    return std::nullopt;
  }
}

std::vector<Eigen::Vector3d> Positions(const Trajectory& trajectory) {
  std::vector<Eigen::Vector3d> positions;
  positions.reserve(trajectory.size());
  for (const TimedPose& pose : trajectory) positions.push_back(pose.T_world_cam.translation());
  return positions;
}

// The two axes along which `positions` extend furthest, in axis order: x-z for a camera-frame
// dataset driving forward (KITTI), x-y for a z-up world (EuRoC, TUM RGB-D).
std::array<int, 2> TopViewAxes(const std::vector<Eigen::Vector3d>& positions) {
  Eigen::Vector3d low = Eigen::Vector3d::Constant(INFINITY), high = Eigen::Vector3d::Constant(-INFINITY);
  for (const Eigen::Vector3d& p : positions) {
    low = low.cwiseMin(p);
    high = high.cwiseMax(p);
  }
  const Eigen::Vector3d extent = high - low;
  std::array<int, 3> order = {0, 1, 2};
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) { return extent[a] > extent[b]; });
  return {std::min(order[0], order[1]), std::max(order[0], order[1])};
}

std::vector<Point> Project(const std::vector<Eigen::Vector3d>& positions, const std::array<int, 2>& axes) {
  std::vector<Point> points;
  points.reserve(positions.size());
  for (const Eigen::Vector3d& p : positions) points.emplace_back(p[axes[0]], p[axes[1]]);
  return points;
}

// Seconds since the first row, or the frame count when the rows carry no time (all timestamps
// equal), with the axis label that goes with it.
struct TimeAxis {
  std::vector<double> x;
  std::string label;
};

TimeAxis TimeOf(const std::vector<FrameRow>& rows) {
  TimeAxis axis;
  const bool timed = !rows.empty() && rows.back().t_ns != rows.front().t_ns;
  axis.label = timed ? "dataset time [s]" : "frame";
  for (size_t i = 0; i < rows.size(); ++i)
    axis.x.push_back(timed ? 1e-9 * static_cast<double>(rows[i].t_ns - rows.front().t_ns) : static_cast<double>(i));
  return axis;
}

// What one sequence contributes to the page: its HTML section and the plots in it.
struct SequencePage {
  std::string html;
  std::vector<Plot> plots;
};

// The top view and the error along the path; adds facts and notes about the trajectories.
void TrajectoryPlots(const ReportSequence& sequence, const std::string& id, std::vector<std::string>* facts,
                     std::vector<std::string>* notes, std::vector<Plot>* plots) {
  const fs::path est_path = sequence.dir / "trajectory.tum", gt_path = sequence.dir / "groundtruth.tum";
  const std::optional<Trajectory> est = ReadPoses(est_path, notes);
  const std::optional<Trajectory> gt = ReadPoses(gt_path, notes);
  std::error_code ec;
  if (!fs::exists(est_path, ec))
    notes->push_back("No estimate: trajectory.tum is missing from " + sequence.dir.string() + ".");
  if (!fs::exists(gt_path, ec))
    notes->push_back(est ? "No ground truth (no groundtruth.tum): the estimate is shown alone, as written, and "
                           "there is no error plot."
                         : "No ground truth (no groundtruth.tum).");
  if (!est && !gt) return;

  const bool mono = sequence.result.sensor == "mono";
  const char* alignment_name = mono ? "Sim(3)" : "SE(3)";
  std::vector<Eigen::Vector3d> est_positions = est ? Positions(*est) : std::vector<Eigen::Vector3d>{};
  const std::vector<Eigen::Vector3d> gt_positions = gt ? Positions(*gt) : std::vector<Eigen::Vector3d>{};
  std::optional<EvalResult> eval;
  if (est && gt) {
    EvalOptions options;
    options.alignment = mono ? Alignment::kSim3 : Alignment::kSE3;
    try {
      eval = Evaluate(*gt, *est, options);
    } catch (const std::exception& e) {
      notes->push_back(std::string("The estimate cannot be aligned onto the ground truth (") + e.what() +
                       "): both are shown as written, without an error plot.");
    }
  }
  if (eval) {
    for (Eigen::Vector3d& p : est_positions)
      p = eval->alignment.scale * eval->alignment.rotation * p + eval->alignment.translation;
    std::string fact = std::string("Estimate aligned onto ground truth by ") + alignment_name;
    if (mono) fact += " (scale " + FixedDecimals(eval->alignment.scale, 4) + ")";
    fact += " over " + std::to_string(eval->pairs.size()) + " matched poses: ATE RMSE " +
            FixedDecimals(eval->ate_m.rmse, 4) + " m, max " + FixedDecimals(eval->ate_m.max, 4) + " m.";
    facts->push_back(fact);
  }
  if (est) facts->push_back(std::to_string(est->size()) + " estimated poses.");

  // Top view: the plane of the two axes along which the ground truth (else the estimate) extends most.
  const std::array<int, 2> axes = TopViewAxes(gt ? gt_positions : est_positions);
  static constexpr std::array<const char*, 3> kAxisNames = {"x", "y", "z"};
  Plot top;
  top.canvas = id + "-top";
  top.title = std::string("Top view (") + kAxisNames[axes[0]] + "-" + kAxisNames[axes[1]] + " plane)";
  if (!gt) top.title += ": no ground truth";
  top.x_label = std::string(kAxisNames[axes[0]]) + " [m]";
  top.y_label = std::string(kAxisNames[axes[1]]) + " [m]";
  top.equal_scale = true;
  if (gt) top.series.push_back({"ground truth", kGroundTruthColour, Thin(Project(gt_positions, axes), kMaxPathPoints)});
  if (est) {
    const std::string label = eval ? std::string("estimate (") + alignment_name + "-aligned)" : "estimate (as written)";
    const std::vector<Point> points = Project(est_positions, axes);
    top.series.push_back({label, kEstimateColour, Thin(points, kMaxPathPoints)});
    top.series.push_back({"start", kStartColour, {points.front()}, false, false, 4});
  }
  plots->push_back(std::move(top));
  if (!eval) return;

  // Position error after alignment, over the distance travelled along the ground truth (drift
  // grows with distance), or over time for a sequence that hardly moves.
  std::vector<double> along(gt_positions.size(), 0.0);
  for (size_t i = 1; i < gt_positions.size(); ++i)
    along[i] = along[i - 1] + (gt_positions[i] - gt_positions[i - 1]).norm();
  const IndexPair first = eval->pairs.front(), last = eval->pairs.back();
  const bool by_distance = along[last.gt_index] - along[first.gt_index] >= kMinPathForDistanceAxis_m;
  std::vector<Point> errors;
  errors.reserve(eval->pairs.size());
  for (const IndexPair& pair : eval->pairs) {
    const double x = by_distance ? along[pair.gt_index] - along[first.gt_index]
                                 : 1e-9 * static_cast<double>((*gt)[pair.gt_index].t_ns - (*gt)[first.gt_index].t_ns);
    errors.emplace_back(x, (gt_positions[pair.gt_index] - est_positions[pair.est_index]).norm());
  }
  Plot error;
  error.canvas = id + "-error";
  error.title = std::string("Position error after ") + alignment_name + " alignment";
  error.x_label = by_distance ? "distance along ground truth [m]" : "ground-truth time [s]";
  error.y_label = "error [m]";
  error.y_from_zero = true;
  error.series.push_back({"position error", kErrorColour, ThinKeepingPeaks(errors, kMaxSeriesPoints)});
  plots->push_back(std::move(error));
}

// Frames/s and keyframes over time from stats.csv; adds facts and notes about the frames.
void FramePlots(const ReportSequence& sequence, const std::string& id, std::vector<std::string>* facts,
                std::vector<std::string>* notes, std::vector<Plot>* plots) {
  const std::optional<std::vector<FrameRow>> all_rows = ReadStats(sequence.dir, notes);
  if (!all_rows) return;
  std::vector<FrameRow> rows;  // frames given to tracking: skipped (unreadable) frames carry no timings
  size_t skipped = 0, lost = 0;
  bool started = false;  // a frame had a pose: later frames without one are lost, in any state
  for (const FrameRow& row : *all_rows) {
    if (row.state == "skipped") {
      ++skipped;
      continue;
    }
    lost += row.state == "lost" || (started && row.state == "not_initialized");
    started = started || row.state == "ok";
    rows.push_back(row);
  }
  facts->push_back("stats.csv: " + std::to_string(all_rows->size()) + " frames, " + std::to_string(lost) + " lost, " +
                   std::to_string(skipped) + " skipped.");
  if (rows.empty()) {
    notes->push_back("stats.csv holds no tracked frame: no frames/s and keyframe plots.");
    return;
  }
  const TimeAxis time = TimeOf(rows);

  // Frames/s over time: 1000 / (extract_ms + track_ms), the mean over the last kFpsWindowFrames
  // frames, i.e. the rate at which one core gets through each frame's extraction and tracking.
  // It is not the wall-clock rate (the pipeline extracts frames in parallel with tracking, and
  // local mapping runs beside both, uncounted), which is why the run's measured wall-clock mean
  // (result.fps) is drawn beside it; t_ns is dataset time, so it cannot give a processing rate.
  Plot fps;
  fps.canvas = id + "-fps";
  fps.title = "Frames/s (1 / (extraction + tracking time), mean of " + std::to_string(kFpsWindowFrames) + " frames)";
  fps.x_label = time.label;
  fps.y_label = "frames/s";
  fps.y_from_zero = true;
  std::vector<Point> rate;
  std::deque<double> window;
  double window_ms = 0;
  for (size_t i = 0; i < rows.size(); ++i) {
    window.push_back(rows[i].work_ms);
    window_ms += rows[i].work_ms;
    if (window.size() > kFpsWindowFrames) {
      window_ms -= window.front();
      window.pop_front();
    }
    if (window_ms > 0) rate.emplace_back(time.x[i], 1000.0 * static_cast<double>(window.size()) / window_ms);
  }
  fps.series.push_back({"per-frame work", kFpsColour, Thin(rate, kMaxSeriesPoints)});
  if (sequence.result.fps > 0)
    fps.series.push_back({"whole run, wall clock",
                          kWallFpsColour,
                          {Point(time.x.front(), sequence.result.fps), Point(time.x.back(), sequence.result.fps)},
                          true,
                          true});
  plots->push_back(std::move(fps));

  // Keyframes over time: those in the map (after culling) and those created so far.
  Plot keyframes;
  keyframes.canvas = id + "-keyframes";
  keyframes.title = "Keyframes";
  keyframes.x_label = time.label;
  keyframes.y_label = "keyframes";
  keyframes.y_from_zero = true;
  std::vector<Point> in_map, created;
  size_t created_so_far = 0;
  for (size_t i = 0; i < rows.size(); ++i) {
    created_so_far += rows[i].keyframe;
    in_map.emplace_back(time.x[i], rows[i].map_keyframes);
    created.emplace_back(time.x[i], static_cast<double>(created_so_far));
  }
  keyframes.series.push_back({"in the map", kMapKeyframesColour, Thin(in_map, kMaxSeriesPoints)});
  keyframes.series.push_back({"created", kCreatedKeyframesColour, Thin(created, kMaxSeriesPoints), true, true});
  plots->push_back(std::move(keyframes));
}

std::string StatusClass(const std::string& status) {
  if (status == "ok") return "ok";
  if (status == "failed") return "failed";
  return "warn";
}

SequencePage BuildSequence(const ReportSequence& sequence, const std::string& id) {
  SequencePage page;
  std::vector<std::string> facts, notes;
  TrajectoryPlots(sequence, id, &facts, &notes, &page.plots);
  FramePlots(sequence, id, &facts, &notes, &page.plots);

  const SequenceResult& result = sequence.result;
  std::string& html = page.html;
  html += "<section class=\"sequence " + StatusClass(result.status) + "\" id=\"" + id + "\">\n";
  html += "<h2>" + HtmlEscape(result.name) + " <span class=\"badge " + StatusClass(result.status) + "\">" +
          HtmlEscape(result.status.empty() ? "unknown" : result.status) + "</span></h2>\n";
  html += "<p class=\"meta\">" + HtmlEscape(result.sensor) + " &middot; " + HtmlEscape(result.dataset) +
          " &middot; folder " + HtmlEscape(sequence.dir.string()) + "</p>\n";
  if (!result.error.empty()) html += "<p class=\"error\">Error: " + HtmlEscape(result.error) + "</p>\n";
  for (const std::string& fact : facts) html += "<p class=\"fact\">" + HtmlEscape(fact) + "</p>\n";
  if (!notes.empty()) {
    html += "<ul class=\"notes\">\n";
    for (const std::string& note : notes) html += "<li>" + HtmlEscape(note) + "</li>\n";
    html += "</ul>\n";
  }
  // The top view on the left, square; the time series stacked on the right.
  const auto canvas = [](const Plot& plot) {
    return "<div class=\"chart\"><canvas id=\"" + plot.canvas + "\"></canvas></div>\n";
  };
  if (!page.plots.empty()) {
    html += "<div class=\"plots\">\n<div class=\"left\">\n";
    for (const Plot& plot : page.plots)
      if (plot.equal_scale) html += canvas(plot);
    html += "</div>\n<div class=\"right\">\n";
    for (const Plot& plot : page.plots)
      if (!plot.equal_scale) html += canvas(plot);
    html += "</div>\n</div>\n";
  }
  html += "<p class=\"back\"><a href=\"#results\">back to the results table</a></p>\n</section>\n";
  return page;
}

// ---- The page ----

const char* kStyle = R"CSS(
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 24px 32px; color: #1d1f23;
       background: #ffffff; font-size: 14px; }
h1 { font-size: 24px; margin: 0 0 4px 0; }
h2 { font-size: 18px; margin: 24px 0 6px 0; }
.lead, .hint, .meta, .fact { color: #4a4f57; margin: 2px 0; }
.table-wrap { overflow-x: auto; border: 1px solid #d5d8dc; }
table { border-collapse: collapse; font-size: 12px; }
th, td { padding: 4px 8px; border-bottom: 1px solid #e4e6e9; white-space: nowrap; text-align: left; }
th { background: #eef0f3; cursor: pointer; user-select: none; position: sticky; top: 0; }
th[data-dir="asc"]::after { content: " \25B2"; }
th[data-dir="desc"]::after { content: " \25BC"; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.error-cell { white-space: normal; min-width: 16em; max-width: 40em; }
tr.failed td { background: #fbe3e3; }
tr.warn td { background: #fff3d6; }
tfoot td { font-weight: 600; background: #f4f5f7; border-top: 2px solid #b9bec5; }
.badge { font-size: 12px; padding: 1px 8px; border-radius: 8px; vertical-align: middle; }
.badge.ok { background: #dcefe0; color: #1e5a2b; }
.badge.failed { background: #c0392b; color: #ffffff; }
.badge.warn { background: #f3c75f; color: #4d3800; }
td.status-failed { color: #b02a1c; font-weight: 700; }
td.status-warn { color: #8a5a00; font-weight: 700; }
section.sequence { border-top: 1px solid #d5d8dc; margin-top: 28px; padding-top: 4px; }
section.failed { border-left: 4px solid #c0392b; padding-left: 12px; }
p.error { color: #b02a1c; font-weight: 600; white-space: pre-wrap; }
ul.notes { color: #6b4e00; background: #fff8e6; padding: 6px 6px 6px 28px; margin: 6px 0; }
.plots { display: grid; grid-template-columns: minmax(0, 1fr) minmax(0, 1fr); gap: 16px; align-items: start;
         margin-top: 8px; }
.right { display: flex; flex-direction: column; gap: 12px; }
.chart { position: relative; min-width: 0; }
.back { font-size: 12px; }
)CSS";

// Records script errors, rejected promises and console errors (Chart.js reports bad data there)
// on the page itself, so that a headless browser can report them (document.body.dataset.errors);
// runs first, before Chart.js is parsed.
const char* kErrorScript = R"JS(
function flatslamRecordError(text) {
  var body = document.body;
  body.dataset.errors = body.dataset.errors ? body.dataset.errors + ' | ' + text : text;
}
window.onerror = function (message, source, line) {
  flatslamRecordError(String(message) + (line ? ' (line ' + line + ')' : ''));
};
window.addEventListener('unhandledrejection', function (event) {
  flatslamRecordError('unhandled rejection: ' + event.reason);
});
(function () {
  var original = console.error;
  console.error = function () {
    flatslamRecordError('console.error: ' + Array.prototype.join.call(arguments, ' '));
    original.apply(console, arguments);
  };
})();
)JS";

// Draws every plot of FLATSLAM_PLOTS, then sets document.body.dataset.charts to the number drawn;
// makes the results table sortable by a click on a column header (empty cells last).
const char* kDrawScript = R"JS(
(function () {
  function equalScale(chart) {
    // One metre as long on both axes: widen the shorter range about its centre.
    var lo = [Infinity, Infinity], hi = [-Infinity, -Infinity];
    chart.data.datasets.forEach(function (d) {
      d.data.forEach(function (p) {
        if (p.x === null || p.y === null) return;
        lo[0] = Math.min(lo[0], p.x); hi[0] = Math.max(hi[0], p.x);
        lo[1] = Math.min(lo[1], p.y); hi[1] = Math.max(hi[1], p.y);
      });
    });
    if (!(hi[0] >= lo[0] && hi[1] >= lo[1])) return;
    for (var pass = 0; pass < 2; ++pass) {  // the tick labels' width changes the area a little
      var a = chart.chartArea, w = a.right - a.left, h = a.bottom - a.top;
      if (!(w > 0 && h > 0)) return;
      var perPx = 1.06 * Math.max(Math.max(hi[0] - lo[0], 1e-3) / w, Math.max(hi[1] - lo[1], 1e-3) / h);
      var cx = (lo[0] + hi[0]) / 2, cy = (lo[1] + hi[1]) / 2, s = chart.options.scales;
      s.x.min = cx - perPx * w / 2; s.x.max = cx + perPx * w / 2;
      s.y.min = cy - perPx * h / 2; s.y.max = cy + perPx * h / 2;
      chart.update();
    }
  }
  var drawn = 0;
  FLATSLAM_PLOTS.forEach(function (plot) {
    try {
      var datasets = plot.series.map(function (s, index) {
        return {
          order: plot.series.length - index,  // later series drawn on top: the estimate over the ground truth
          label: s.label, showLine: s.line, borderColor: s.colour, backgroundColor: s.colour, borderWidth: 2,
          borderDash: s.dashed ? [6, 4] : [], pointRadius: s.marker, pointHoverRadius: s.marker + 2,
          data: s.points.map(function (p) { return {x: p[0], y: p[1]}; })
        };
      });
      var chart = new Chart(document.getElementById(plot.canvas), {
        type: 'scatter',
        data: {datasets: datasets},
        options: {
          animation: false, responsive: true, maintainAspectRatio: true, aspectRatio: plot.equal ? 1 : 2.9,
          plugins: {title: {display: true, text: plot.title}, legend: {
            position: 'top',
            labels: {boxWidth: 28, boxHeight: 3, sort: function (a, b) { return a.datasetIndex - b.datasetIndex; }}
          }},
          scales: {
            x: {type: 'linear', title: {display: true, text: plot.x}, ticks: {includeBounds: !plot.equal}},
            y: {type: 'linear', title: {display: true, text: plot.y}, ticks: {includeBounds: !plot.equal}, beginAtZero: plot.zero}
          }
        }
      });
      if (plot.equal) equalScale(chart);
      ++drawn;
    } catch (e) {
      window.onerror('plot ' + plot.canvas + ': ' + e, '', 0);
    }
  });
  document.body.dataset.charts = String(drawn);

  var table = document.getElementById('results-table');
  if (!table || !table.tHead || !table.tBodies.length) return;
  var heads = table.tHead.rows[0].cells;
  Array.prototype.forEach.call(heads, function (th, column) {
    th.addEventListener('click', function () {
      var dir = th.dataset.dir === 'asc' ? -1 : 1;
      Array.prototype.forEach.call(heads, function (h) { delete h.dataset.dir; });
      th.dataset.dir = dir === 1 ? 'asc' : 'desc';
      function key(row) {
        var text = row.cells[column].textContent.trim();
        if (text === '') return null;
        var number = Number(text);
        return isNaN(number) ? text : number;
      }
      var body = table.tBodies[0];
      var rows = Array.prototype.slice.call(body.rows);
      rows.sort(function (a, b) {
        var x = key(a), y = key(b);
        if (x === null || y === null) return x === y ? 0 : (x === null ? 1 : -1);
        if (typeof x === 'number' && typeof y === 'number') return dir * (x - y);
        return dir * String(x).localeCompare(String(y));
      });
      rows.forEach(function (row) { body.appendChild(row); });
    });
  });
})();
)JS";

// One row of the results table: a sequence, whose name links to its section `anchor`, or the
// summary row (anchor empty), which has no status.
std::string TableRow(const SequenceResult& result, const std::string& anchor) {
  const std::vector<std::string>& columns = ResultColumns();
  const std::vector<std::string> cells = ResultCells(result);
  const bool summary = anchor.empty();
  std::string row = "<tr class=\"" + (summary ? std::string("summary") : StatusClass(result.status)) + "\">";
  for (size_t c = 0; c < cells.size() && c < columns.size(); ++c) {
    const std::string& name = columns[c];
    std::string cls;
    if (name == "error")
      cls = "error-cell";
    else if (name == "status" && !summary && result.status != "ok")
      cls = "status-" + StatusClass(result.status);
    else if (IsNumber(cells[c]))
      cls = "num";
    row += cls.empty() ? "<td" : "<td class=\"" + cls + "\"";
    // The error is the last column, often scrolled out of view: the status cell shows it on hover.
    if (name == "status" && !result.error.empty()) row += " title=\"" + HtmlEscape(result.error) + "\"";
    row += ">";
    if (name == "sequence" && !summary)
      row += "<a href=\"#" + anchor + "\">" + HtmlEscape(cells[c]) + "</a>";
    else
      row += HtmlEscape(cells[c]);
    row += "</td>";
  }
  return row + "</tr>\n";
}

}  // namespace

void WriteHtmlReport(const std::filesystem::path& html, const std::string& title,
                     const std::vector<ReportSequence>& sequences) {
  const std::string chart_js = InlineScript(ReadChartJs());  // first: a missing Chart.js fails fast

  std::vector<SequenceResult> rows;
  std::vector<std::string> anchors;
  std::vector<SequencePage> pages;
  size_t failed = 0, other = 0;
  for (size_t i = 0; i < sequences.size(); ++i) {
    rows.push_back(sequences[i].result);
    anchors.push_back(AnchorId(i, sequences[i].result.name));
    pages.push_back(BuildSequence(sequences[i], anchors.back()));
    failed += sequences[i].result.status == "failed";
    other += sequences[i].result.status != "failed" && sequences[i].result.status != "ok";
  }

  std::string page;
  page += "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n";
  page += "<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n";
  page += "<title>" + HtmlEscape(title) + "</title>\n<style>" + kStyle + "</style>\n</head>\n<body>\n";
  page += std::string("<script>") + kErrorScript + "</script>\n";
  page += "<script>\n" + chart_js + "\n</script>\n";

  page += "<h1>" + HtmlEscape(title) + "</h1>\n";
  page += "<p class=\"lead\">" + std::to_string(sequences.size()) +
          " sequence(s): " + std::to_string(sequences.size() - failed - other) + " ok, " + std::to_string(failed) +
          " failed" + (other ? ", " + std::to_string(other) + " interrupted or unknown" : std::string()) + ".</p>\n";
  page +=
      "<p class=\"hint\">Per sequence below: the top view of the estimate aligned onto the ground truth "
      "(Sim(3) for monocular runs, SE(3) otherwise), the position error along the path, the frames/s "
      "of extraction and tracking work (mean of " +
      std::to_string(kFpsWindowFrames) +
      " frames; the dashed line is the whole run's wall-clock rate) and the keyframes over time.</p>\n";

  page += "<h2 id=\"results\">Results</h2>\n";
  if (sequences.empty()) {
    page += "<p>No sequences.</p>\n";
  } else {
    page += "<div class=\"table-wrap\"><table id=\"results-table\">\n<thead><tr>";
    for (const std::string& column : ResultColumns())
      page += "<th title=\"click to sort\">" + HtmlEscape(column) + "</th>";
    page += "</tr></thead>\n<tbody>\n";
    for (size_t i = 0; i < rows.size(); ++i) page += TableRow(rows[i], anchors[i]);
    page += "</tbody>\n<tfoot>\n" + TableRow(SummarizeResults(rows), "") + "</tfoot>\n</table></div>\n";
    page +=
        "<p class=\"hint\">Click a column header to sort; the last row sums counts and takes medians of "
        "metrics.</p>\n";
  }

  std::string plots_json = "[";
  for (const SequencePage& sequence : pages) {
    page += sequence.html;
    for (const Plot& plot : sequence.plots) {
      if (plots_json.size() > 1) plots_json += ",\n";
      plots_json += PlotJson(plot);
    }
  }
  plots_json += "]";
  page += "<script>\nvar FLATSLAM_PLOTS = " + plots_json + ";\n</script>\n";
  page += std::string("<script>") + kDrawScript + "</script>\n</body>\n</html>\n";

  WriteFileAtomically(html, [&](std::FILE* file) { std::fwrite(page.data(), 1, page.size(), file); });
}

}  // namespace flatslam
