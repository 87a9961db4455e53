// The results of SLAM runs as a table: one row per sequence, written as results.csv,
// results.json and a Markdown table, read back to join the results of several batches.
// Concurrency: plain values and free functions.
#pragma once

#include <cstddef>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace flatslam {

// One sequence's run. Metrics that need ground truth are empty without it; the KITTI metric is
// empty when the path is shorter than its shortest segment (100 m).
struct SequenceResult {
  std::string name;     // unique in a batch; the sequence's folder under the batch's output
  std::string dataset;  // what was opened (path or synth:SPEC)
  std::string sensor;   // mono, stereo or rgbd
  std::string status;   // ok, failed (error says why) or interrupted
  std::string error;
  size_t input = 0;    // position in the batch's full list of inputs (shards keep it; collect sorts by it)
  size_t frames = 0;   // frames given to SLAM
  size_t tracked = 0;  // frames with a pose in the trajectory
  size_t lost = 0, skipped = 0, keyframes = 0, map_points = 0, loops = 0;
  size_t segments = 0;  // new map segments started where tracking failed (a monocular one has its own scale)
  std::optional<double> ate_se3_m, ate_sim3_m, scale;  // ATE RMSE after SE(3) / Sim(3) alignment
  std::optional<double> rpe_m, rpe_deg;                // RPE RMSE per frame, SE(3)-aligned
  std::optional<double> path_m;                        // ground-truth path length over the trajectory
  std::optional<double> kitti_t_rel_pct, kitti_r_rel_deg_per_100m;
  // Stereo: measured minus predicted disparity of the map's points (a rig's rectification error,
  // mapping/rig_check.h), pixels; what the run took off already is not included.
  std::optional<double> rig_offset_px;
  // Monocular runs through a refined camera: the one their young map refined and started over
  // with (SlamRunResult::camera_refit), or the one of the map they continued or took their camera
  // from (--camera-from); its radial k1 and focal-length scale. Empty: the given camera.
  std::optional<double> camera_refit_k1, camera_refit_focal_scale;
  double wall_s = 0;            // from opening the dataset to the results computed
  double fps = 0;               // frames / tracking wall time
  double cpu_ms_per_frame = 0;  // work per frame: extraction, tracking and local mapping time / frames
  double peak_rss_mib = 0;      // the process's peak resident set while the sequence ran
};

// Column names, in the order of every table.
[[nodiscard]] const std::vector<std::string>& ResultColumns();
// The row as text, one cell per column: numbers in fixed precision, empty where unknown.
[[nodiscard]] std::vector<std::string> ResultCells(const SequenceResult& result);

// Totals (frames, lost, skipped, keyframes, loops, wall time) and medians (every metric, frames/s,
// CPU time per frame, peak RSS) over the rows; name "summary". Empty metrics are left out of
// medians.
[[nodiscard]] SequenceResult SummarizeResults(const std::vector<SequenceResult>& rows);

// results.csv: a header of ResultColumns(), then one line per row (summary not included).
// Text cells are quoted when they hold a comma, quote or line break. Written atomically.
void WriteResultsCsv(const std::filesystem::path& path, const std::vector<SequenceResult>& rows);
// Reads a file written by WriteResultsCsv. Throws flatslam::Error naming the file, line and
// column of anything it cannot read.
[[nodiscard]] std::vector<SequenceResult> ReadResultsCsv(const std::filesystem::path& path);

// results.json: {"sequences": [...], "summary": {...}}, numbers as numbers, unknown as null.
void WriteResultsJson(const std::filesystem::path& path, const std::vector<SequenceResult>& rows);

// A JSON string literal (quotes included) that may also sit inside an HTML <script> element:
// '<', '>' and '&' are written as \u escapes, so no "</script" or "<!--" can appear; U+2028 and
// U+2029 are escaped for JavaScript engines that do not allow them in string literals.
[[nodiscard]] std::string JsonString(std::string_view text);

// A Markdown table of the rows and the summary row (the main columns only, for a terminal).
[[nodiscard]] std::string ResultsMarkdown(const std::vector<SequenceResult>& rows);

}  // namespace flatslam
