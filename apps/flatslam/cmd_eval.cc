// flatslam eval: scores an estimated trajectory against ground truth (ATE, RPE, KITTI metric).
#include <cmath>
#include <cstdio>
#include <sstream>
#include <string>
#include <vector>

#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "trajectory/metrics.h"
#include "trajectory/trajectory_io.h"

namespace flatslam::app {

const char* const kEvalUsage =
    "usage: flatslam eval EST GT [options]\n"
    "       flatslam eval EST1 GT1 EST2 GT2 [...] [options]\n"
    "\n"
    "Scores the estimated trajectory EST against the ground truth GT: ATE after alignment,\n"
    "RPE per frame and per distance, and the KITTI odometry metric (segments of 100..800 m).\n"
    "Several pairs: estimates in one frame (the agents of a merged map, each exported with\n"
    "`flatslam map export --agent N`), each paired with its own ground truth, under ONE alignment\n"
    "of all of them; prints each one's ATE under it and aligned alone, and all together.\n"
    "Files may be TUM (t tx ty tz qx qy qz qw), KITTI (12 numbers a line) or EuRoC csv;\n"
    "the format is detected unless given. Poses are paired by timestamp (nearest, as evo);\n"
    "two KITTI files without times and of equal length are paired by index.\n"
    "\n"
    "options:\n"
    "  --align se3|sim3|none   alignment of EST onto GT before every metric (default se3;\n"
    "                          sim3 for monocular estimates)\n"
    "  --est-format F          tum, kitti, euroc or auto (default auto); --gt-format likewise\n"
    "  --max-diff SECONDS      largest timestamp difference of a pair (default 0.02)\n"
    "  --est-times FILE        KITTI times.txt of EST (seconds a line); --gt-times likewise\n"
    "  --rpe-delta-m M         RPE distance step along the GT path in metres (default 1; 0 = off)\n"
    "  --json                  print one JSON object instead of the table\n";

namespace {

// One input trajectory and how it was read.
struct Input {
  std::string path;
  TrajectoryFormat format = TrajectoryFormat::kAuto;
  bool has_times = true;  // false for KITTI files read without times.txt
  Trajectory trajectory;
};

TrajectoryFormat FormatFlag(const Args& args, const std::string& name) {
  const std::string value = args.get_or(name, "auto");
  const auto format = ParseTrajectoryFormat(value);
  if (!format) throw UsageError{"option --" + name + ": '" + value + "' is not one of tum, kitti, euroc, auto"};
  return *format;
}

Input Load(const std::string& path, TrajectoryFormat format, const std::optional<std::string>& times_path,
           const char* role) {
  Input input;
  input.path = path;
  input.format = format == TrajectoryFormat::kAuto ? DetectTrajectoryFormat(path) : format;
  TrajectoryReadOptions options;
  options.format = input.format;
  input.trajectory = ReadTrajectory(path, options);
  input.has_times = input.format != TrajectoryFormat::kKitti || times_path.has_value();
  if (times_path) {
    FLATSLAM_CHECK(input.format == TrajectoryFormat::kKitti, "--", role, "-times: ", path, " is a ",
                   TrajectoryFormatName(input.format), " file with its own timestamps; only KITTI files take times");
    const std::vector<int64_t> times_ns = ReadKittiTimes(*times_path);
    FLATSLAM_CHECK(times_ns.size() == input.trajectory.size(), path, " has ", input.trajectory.size(), " poses but ",
                   *times_path, " has ", times_ns.size(), " times");
    for (size_t i = 0; i < times_ns.size(); ++i) input.trajectory[i].t_ns = times_ns[i];
  }
  return input;
}

// ---- JSON ----

std::string JsonString(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char buffer[8];
      std::snprintf(buffer, sizeof(buffer), "\\u%04x", c);
      out += buffer;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

std::string JsonNumber(double value) {
  if (!std::isfinite(value)) return "null";
  char buffer[32];
  std::snprintf(buffer, sizeof(buffer), "%.10g", value);
  return buffer;
}

std::string JsonStats(const ErrorStats& s) {
  if (s.count == 0) return "null";
  std::ostringstream out;
  out << "{\"count\": " << s.count << ", \"rmse\": " << JsonNumber(s.rmse) << ", \"mean\": " << JsonNumber(s.mean)
      << ", \"median\": " << JsonNumber(s.median) << ", \"std\": " << JsonNumber(s.std)
      << ", \"min\": " << JsonNumber(s.min) << ", \"max\": " << JsonNumber(s.max) << "}";
  return out.str();
}

std::string JsonInput(const Input& input) {
  std::ostringstream out;
  out << "{\"path\": " << JsonString(input.path) << ", \"format\": \"" << TrajectoryFormatName(input.format)
      << "\", \"poses\": " << input.trajectory.size() << "}";
  return out.str();
}

std::string JsonRpe(const RpeResult& rpe, const char* delta_key, const std::string& delta_value) {
  std::ostringstream out;
  out << "{\"" << delta_key << "\": " << delta_value << ", \"pairs\": " << rpe.pairs
      << ",\n      \"translation_m\": " << JsonStats(rpe.translation_m)
      << ",\n      \"rotation_deg\": " << JsonStats(rpe.rotation_deg) << "}";
  return out.str();
}

void PrintJson(const Input& est, const Input& gt, const EvalOptions& options, const EvalResult& r) {
  std::ostringstream out;
  const AlignmentResult& a = r.alignment;
  out << "{\n  \"estimate\": " << JsonInput(est) << ",\n  \"ground_truth\": " << JsonInput(gt)
      << ",\n  \"association\": {\"method\": \"" << (options.pair_by_index ? "index" : "time")
      << "\", \"max_diff_s\": " << JsonNumber(options.association.max_diff_s) << ", \"pairs\": " << r.pairs.size()
      << "},\n  \"alignment\": {\"type\": \"" << AlignmentName(options.alignment)
      << "\", \"scale\": " << JsonNumber(a.scale) << ", \"rotation\": [";
  for (int i = 0; i < 3; ++i) {
    out << (i ? ", [" : "[");
    for (int j = 0; j < 3; ++j) out << (j ? ", " : "") << JsonNumber(a.rotation(i, j));
    out << "]";
  }
  out << "], \"translation\": [" << JsonNumber(a.translation.x()) << ", " << JsonNumber(a.translation.y()) << ", "
      << JsonNumber(a.translation.z()) << "]},\n  \"ate_m\": " << JsonStats(r.ate_m)
      << ",\n  \"rpe_frames\": " << JsonRpe(r.rpe_frames, "delta_frames", std::to_string(options.rpe_delta_frames))
      << ",\n  \"rpe_distance\": " << JsonRpe(r.rpe_distance, "delta_m", JsonNumber(options.rpe_delta_m))
      << ",\n  \"kitti\": {\"available\": " << (r.kitti.available ? "true" : "false")
      << ", \"segments\": " << r.kitti.segments << ", \"path_length_m\": " << JsonNumber(r.kitti.path_length_m)
      << ", \"t_rel_percent\": " << (r.kitti.available ? JsonNumber(r.kitti.t_rel_percent) : "null")
      << ", \"r_rel_deg_per_100m\": " << (r.kitti.available ? JsonNumber(r.kitti.r_rel_deg_per_100m) : "null")
      << "}\n}\n";
  std::fputs(out.str().c_str(), stdout);
}

// ---- Text ----

void PrintStatsRow(const std::string& label, const ErrorStats& s) {
  std::printf("  %-20s %10.6f %10.6f %10.6f %10.6f\n", label.c_str(), s.rmse, s.mean, s.median, s.max);
}

void PrintText(const Input& est, const Input& gt, const EvalOptions& options, const EvalResult& r) {
  std::printf("estimate      %s (%s, %zu poses)\n", est.path.c_str(), TrajectoryFormatName(est.format),
              est.trajectory.size());
  std::printf("ground truth  %s (%s, %zu poses)\n", gt.path.c_str(), TrajectoryFormatName(gt.format),
              gt.trajectory.size());
  if (options.pair_by_index) {
    std::printf("pairs         %zu (by index)\n", r.pairs.size());
  } else {
    std::printf("pairs         %zu (by time, max diff %g s)\n", r.pairs.size(), options.association.max_diff_s);
  }
  std::printf("alignment     %s, scale %.6f\n\n", AlignmentName(options.alignment), r.alignment.scale);
  std::printf("  %-20s %10s %10s %10s %10s\n", "", "rmse", "mean", "median", "max");
  PrintStatsRow("ATE [m]", r.ate_m);
  const std::string frames = "RPE " + std::to_string(options.rpe_delta_frames) + " frame";
  if (r.rpe_frames.pairs > 0) {
    PrintStatsRow(frames + " [m]", r.rpe_frames.translation_m);
    PrintStatsRow(frames + " [deg]", r.rpe_frames.rotation_deg);
  } else {
    std::printf("  %-20s n/a (fewer than 2 pairs)\n", frames.c_str());
  }
  if (options.rpe_delta_m > 0) {
    char distance[64];
    std::snprintf(distance, sizeof(distance), "RPE %g m", options.rpe_delta_m);
    if (r.rpe_distance.pairs > 0) {
      PrintStatsRow(std::string(distance) + " [m]", r.rpe_distance.translation_m);
      PrintStatsRow(std::string(distance) + " [deg]", r.rpe_distance.rotation_deg);
    } else {
      std::printf("  %-20s n/a (ground-truth path %.1f m)\n", distance, r.kitti.path_length_m);
    }
  }
  std::printf("\n");
  if (r.kitti.available) {
    std::printf("KITTI         t_rel %.4f %%, r_rel %.4f deg/100m (%zu segments)\n", r.kitti.t_rel_percent,
                r.kitti.r_rel_deg_per_100m, r.kitti.segments);
  } else {
    std::printf("KITTI         t_rel n/a, r_rel n/a (ground-truth path %.1f m, shortest segment %g m)\n",
                r.kitti.path_length_m, options.kitti.lengths_m.front());
  }
}

// Several estimates under one alignment (EvaluateJointAte).
void PrintJoint(const std::vector<Input>& est, const std::vector<Input>& gt, const EvalOptions& options,
                const JointAteResult& r, bool json) {
  if (json) {
    std::ostringstream out;
    out << "{\n  \"alignment\": {\"type\": \"" << AlignmentName(options.alignment)
        << "\", \"scale\": " << JsonNumber(r.alignment.scale) << "},\n  \"estimates\": [";
    for (size_t k = 0; k < est.size(); ++k) {
      out << (k ? ",\n    " : "\n    ") << "{\"estimate\": " << JsonInput(est[k])
          << ", \"ground_truth\": " << JsonInput(gt[k]) << ", \"pairs\": " << r.pairs[k]
          << ",\n     \"ate_m\": " << JsonStats(r.ate_m[k])
          << ",\n     \"own_alignment_ate_m\": " << JsonStats(r.own_ate_m[k]) << "}";
    }
    out << "],\n  \"ate_m\": " << JsonStats(r.all_m) << "\n}\n";
    std::fputs(out.str().c_str(), stdout);
    return;
  }
  std::printf("alignment     %s, one for all %zu estimates, scale %.6f\n", AlignmentName(options.alignment), est.size(),
              r.alignment.scale);
  for (size_t k = 0; k < est.size(); ++k) {
    std::printf("estimate %-4zu %s against %s: %zu pairs, ATE rmse %.6f m (aligned alone %.6f m)\n", k + 1,
                est[k].path.c_str(), gt[k].path.c_str(), r.pairs[k], r.ate_m[k].rmse, r.own_ate_m[k].rmse);
  }
  std::printf("all           %zu pairs, ATE rmse %.6f m\n", r.all_m.count, r.all_m.rmse);
}

}  // namespace

int RunEval(const std::vector<std::string>& argv) {
  const Args args(argv, {"align", "est-format", "gt-format", "max-diff", "est-times", "gt-times", "rpe-delta-m"},
                  {"json"});
  if (args.help()) {
    std::fputs(kEvalUsage, stdout);
    return 0;
  }
  const size_t files = args.positional().size();
  if (files < 2 || files % 2 != 0)
    throw UsageError{"expected pairs of files (EST GT [EST2 GT2 ...]), got " + std::to_string(files)};
  if (files > 2 && (args.get("est-times") || args.get("gt-times")))
    throw UsageError{"--est-times and --gt-times take one pair of files (EST GT)"};

  EvalOptions options;
  const std::string align = args.get_or("align", "se3");
  const auto alignment = ParseAlignment(align);
  if (!alignment) throw UsageError{"option --align: '" + align + "' is not one of se3, sim3, none"};
  options.alignment = *alignment;
  options.association.max_diff_s = args.get_double("max-diff", options.association.max_diff_s);
  if (options.association.max_diff_s < 0) throw UsageError{"option --max-diff must not be negative"};
  options.rpe_delta_m = args.get_double("rpe-delta-m", options.rpe_delta_m);
  if (options.rpe_delta_m < 0) throw UsageError{"option --rpe-delta-m must not be negative"};
  const TrajectoryFormat est_format = FormatFlag(args, "est-format");
  const TrajectoryFormat gt_format = FormatFlag(args, "gt-format");

  if (files > 2) {
    std::vector<Input> est, gt;
    std::vector<Trajectory> est_trajectories, gt_trajectories;
    for (size_t i = 0; i < files; i += 2) {
      est.push_back(Load(args.positional()[i], est_format, std::nullopt, "est"));
      gt.push_back(Load(args.positional()[i + 1], gt_format, std::nullopt, "gt"));
      for (const Input* input : {&est.back(), &gt.back()})
        FLATSLAM_CHECK(input->has_times, input->path,
                       " is a KITTI file without timestamps: several pairs are paired by time (TUM or EuRoC files)");
      est_trajectories.push_back(est.back().trajectory);
      gt_trajectories.push_back(gt.back().trajectory);
    }
    PrintJoint(est, gt, options, EvaluateJointAte(gt_trajectories, est_trajectories, options), args.has("json"));
    return 0;
  }
  const Input est = Load(args.positional()[0], est_format, args.get("est-times"), "est");
  const Input gt = Load(args.positional()[1], gt_format, args.get("gt-times"), "gt");

  // KITTI poses without times.txt carry no real timestamps: pair them by index when both are
  // such files, and refuse to match them against real times.
  if (!est.has_times && !gt.has_times) {
    FLATSLAM_CHECK(est.trajectory.size() == gt.trajectory.size(), "KITTI files without times are paired by index, but ",
                   est.path, " has ", est.trajectory.size(), " poses and ", gt.path, " has ", gt.trajectory.size(),
                   "; pass --est-times and --gt-times");
    options.pair_by_index = true;
  } else if (!est.has_times || !gt.has_times) {
    const Input& untimed = est.has_times ? gt : est;
    Fail(untimed.path, " is a KITTI file without timestamps and the other file has real ones; pass --",
         est.has_times ? "gt" : "est", "-times FILE (KITTI times.txt)");
  }

  const EvalResult result = Evaluate(gt.trajectory, est.trajectory, options);
  if (args.has("json")) {
    PrintJson(est, gt, options, result);
  } else {
    PrintText(est, gt, options, result);
  }
  return 0;
}

}  // namespace flatslam::app
