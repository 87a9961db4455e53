// flatslam batch: many sequences in one process on every core, one results table and a report.
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <mutex>
#include <set>
#include <thread>

#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "io/manifest.h"
#include "jobs/batch.h"
#include "jobs/sequence_run.h"
#include "report/html_report.h"
#include "report/results.h"
#include "stop_signals.h"
#include "place/vocabulary.h"

namespace flatslam::app {

const char* const kBatchUsage =
    "usage: flatslam batch INPUT... [--out DIR] [--jobs N] [--memory BYTES] [--shard I/N] [--quiet]\n"
    "                      [--sensor mono|stereo|rgbd] [--settings FILE] [--config FILE] [--set K=V,...]\n"
    "                      [--max-frames N] [--seed N] [--vocabulary FILE|none]\n"
    "                      [--keep-camera | --camera-from MAP] [--deterministic]\n"
    "       flatslam batch --collect DIR... --out DIR\n\n"
    "Runs SLAM over many sequences in one process, as many at once as --jobs and --memory allow, all\n"
    "sharing the cores and one vocabulary, and writes one results table and one report.\n"
    "INPUT is a dataset folder (KITTI sequence, EuRoC, TUM RGB-D), a folder of dataset folders (or a\n"
    "KITTI root with sequences/), synth:SPEC, or a manifest file, one sequence per line:\n"
    "    DATASET [--name N] [--sensor S] [--settings F] [--config F] [--set K=V,...] [--seed N]\n"
    "            [--max-frames N] [--keep-camera] [--camera-from MAP]\n"
    "or YAML, a list of mappings:\n"
    "    - path: DATASET\n"
    "      name: N\n"
    "      sensor: stereo\n"
    "      options:\n"
    "        orb.features: 2000\n"
    "(also settings, config, seed, max_frames, keep_camera, camera_from). Relative paths are from\n"
    "the manifest's folder; the flags above apply to every sequence that does not set its own.\n"
    "  --keep-camera    monocular sequences run with the camera as given (as flatslam run\n"
    "                   --keep-camera): by default each checks its camera against its young map and\n"
    "                   may start over with the refined one, and checks its whole map after its\n"
    "                   last frame (results: camera_refit_k1, camera_refit_focal_scale)\n"
    "  --camera-from MAP  monocular sequences run with the camera the saved map's session used (as\n"
    "                   flatslam run --camera-from), not checked: their maps share it and merge\n"
    "  --out DIR        results (default ./flatslam-batch): DIR/<sequence>/ holds what flatslam run\n"
    "                   --out writes (trajectories, stats.csv, groundtruth.tum, results.csv,\n"
    "                   report.html); DIR/results.csv, DIR/results.json and DIR/report.html cover\n"
    "                   every sequence; the table is also printed (Markdown)\n"
    "  --jobs N         sequences at once (default: twice the number of cores)\n"
    "  --memory BYTES   resident-set budget, e.g. 6G or 800M (default: 80% of the memory available\n"
    "                   at the start); a sequence starts only when the largest one measured so far\n"
    "                   still fits, so a batch does not swap\n"
    "  --shard I/N      run only the I-th of N deterministic slices of the inputs (0 <= I < N):\n"
    "                   positions I, I+N, I+2N, ... of the expanded list; collect the slices with\n"
    "                   --collect (see docs/batch/ for Slurm, Kubernetes and GNU parallel)\n"
    "  --collect DIR... join the results of batches (shards) into one table and report in --out\n"
    "  --deterministic  global bundle adjustment inline too: every sequence gives the output of\n"
    "                   its single deterministic run\n"
    "  --quiet          no progress lines\n"
    "Progress: on a terminal one line per running sequence and an overall line with an ETA; else a\n"
    "plain line every 10 s. A sequence that fails is reported and the batch goes on; the exit code is 1\n"
    "when any failed, 130/143 when interrupted (the first SIGINT/SIGTERM stops starting sequences and\n"
    "ends the running ones early, writing everything computed), else 0.\n";

namespace {

const std::set<std::string> kBatchFlags = {"out",    "jobs", "memory",     "shard", "sensor",    "settings",
                                           "config", "set",  "max-frames", "seed",  "vocabulary", "camera-from"};
const std::set<std::string> kBatchSwitches = {"quiet", "deterministic", "collect", "keep-camera"};

// "6G", "800M", "512K" or plain bytes -> MiB.
double ParseBytesMiB(const std::string& text) {
  size_t used = 0;
  double value = 0;
  try {
    value = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  double scale = 1.0 / (1024.0 * 1024.0);
  if (used > 0 && used + 1 == text.size()) {
    switch (std::toupper(static_cast<unsigned char>(text.back()))) {
      case 'K':
        scale = 1.0 / 1024.0;
        break;
      case 'M':
        scale = 1.0;
        break;
      case 'G':
        scale = 1024.0;
        break;
      case 'T':
        scale = 1024.0 * 1024.0;
        break;
      default:
        used = 0;
    }
    if (used > 0) ++used;
  }
  if (used == 0 || used != text.size() || !(value > 0))
    throw UsageError{"--memory: cannot read '" + text + "' (a number of bytes, or with K, M, G or T)"};
  return value * scale;
}

std::pair<size_t, size_t> ParseShard(const std::string& text) {
  const size_t slash = text.find('/');
  size_t index = 0, count = 0, used_a = 0, used_b = 0;
  try {
    if (slash == std::string::npos) throw std::invalid_argument(text);
    index = std::stoull(text.substr(0, slash), &used_a);
    count = std::stoull(text.substr(slash + 1), &used_b);
  } catch (const std::exception&) {
    used_a = 0;
  }
  if (used_a != slash || used_b != text.size() - slash - 1 || count == 0 || index >= count || text[0] == '-')
    throw UsageError{"--shard: cannot read '" + text + "' (expected I/N with 0 <= I < N)"};
  return {index, count};
}

std::string Duration(double seconds) {
  if (seconds < 0) return "?";
  char text[32];
  const long s = std::lround(seconds);
  if (s >= 3600)
    std::snprintf(text, sizeof(text), "%ldh%02ldm", s / 3600, s / 60 % 60);
  else if (s >= 60)
    std::snprintf(text, sizeof(text), "%ldm%02lds", s / 60, s % 60);
  else
    std::snprintf(text, sizeof(text), "%lds", s);
  return text;
}

std::string OverallLine(const BatchProgress& p) {
  char line[256];
  const double fps = p.elapsed_s > 0 ? static_cast<double>(p.frames_done) / p.elapsed_s : 0;
  std::snprintf(line, sizeof(line),
                "batch: %zu of %zu done, %zu running, %zu frames, %.1f frames/s, RSS %.0f of %.0f MiB, %s elapsed, "
                "ETA %s",
                p.finished, p.sequences.size(), p.running, p.frames_done, fps, p.rss_mib, p.budget_mib,
                Duration(p.elapsed_s).c_str(), Duration(p.eta_s).c_str());
  return line;
}

// Progress on a terminal: the block of lines drawn last time is redrawn in place; a message
// (a sequence finished, a warning) replaces the block and the next draw starts below it. Draw
// and Message may come from different threads.
class TerminalProgress {
 public:
  void Draw(const BatchProgress& p) {
    std::string text;
    size_t lines = 0;
    for (const SequenceProgress& s : p.sequences) {
      if (s.state != "running") continue;
      char line[256];
      const std::string total = s.frames_total > 0 ? std::to_string(s.frames_total) : "?";
      std::snprintf(line, sizeof(line), "  %-32.32s %6zu / %-6s frames  %6.1f frames/s  %s", s.name.c_str(),
                    s.frames_done, total.c_str(), s.fps, s.tracking.c_str());
      text += std::string(line) + "\n";
      ++lines;
    }
    text += OverallLine(p) + "\n";
    const std::lock_guard<std::mutex> lock(mutex_);
    std::fputs((BackToBlock() + text).c_str(), stderr);
    lines_ = lines + 1;
    std::fflush(stderr);
  }
  void Message(const std::string& line) {
    const std::lock_guard<std::mutex> lock(mutex_);
    std::fputs((BackToBlock() + line + "\n").c_str(), stderr);
    lines_ = 0;
    std::fflush(stderr);
  }

 private:
  // Cursor up to the block's first line, the block cleared; empty when nothing is drawn.
  std::string BackToBlock() const { return lines_ > 0 ? "\x1b[" + std::to_string(lines_) + "F\x1b[J" : std::string(); }
  std::mutex mutex_;
  size_t lines_ = 0;
};

// Writes the batch's table and report, prints the table; returns the exit code for the rows.
int WriteBatchResults(const std::filesystem::path& out, std::vector<ReportSequence> sequences) {
  std::sort(sequences.begin(), sequences.end(),
            [](const ReportSequence& a, const ReportSequence& b) { return a.result.input < b.result.input; });
  std::vector<SequenceResult> rows;
  for (const ReportSequence& s : sequences) rows.push_back(s.result);
  std::filesystem::create_directories(out);
  WriteResultsCsv(out / "results.csv", rows);
  WriteResultsJson(out / "results.json", rows);
  std::string report_note = (out / "report.html").string();
  try {
    WriteHtmlReport(out / "report.html", "flatslam batch: " + std::to_string(rows.size()) + " sequences", sequences);
  } catch (const Error& e) {
    report_note = std::string("not written: ") + e.what();
  }
  std::printf("%s\n", ResultsMarkdown(rows).c_str());
  size_t failed = 0;
  for (const SequenceResult& r : rows) failed += r.status == "failed";
  std::printf("results       %s/results.csv, %s/results.json\nreport        %s\n", out.c_str(), out.c_str(),
              report_note.c_str());
  for (const SequenceResult& r : rows)
    if (r.status == "failed") std::printf("failed        %s: %s\n", r.name.c_str(), r.error.c_str());
  return failed > 0 ? 1 : 0;
}

int Collect(const Args& args, const std::filesystem::path& out) {
  if (args.positional().empty()) throw UsageError{"--collect needs the result folders of the batches to join"};
  std::vector<ReportSequence> sequences;
  std::map<std::string, std::string> seen;  // name -> folder it came from
  std::set<size_t> inputs;
  for (const std::string& dir : args.positional()) {
    const std::filesystem::path table = std::filesystem::path(dir) / "results.csv";
    FLATSLAM_CHECK(std::filesystem::exists(table), dir, ": no results.csv (not the --out folder of a batch)");
    for (SequenceResult& row : ReadResultsCsv(table)) {
      FLATSLAM_CHECK(!seen.count(row.name), table.string(), ": sequence '", row.name, "' is also in ", seen[row.name],
                     " (shards of one batch hold each sequence once)");
      FLATSLAM_CHECK(!inputs.count(row.input), table.string(), ": input position ", row.input,
                     " appears twice (batches of different inputs?)");
      seen[row.name] = dir;
      inputs.insert(row.input);
      const std::filesystem::path folder = std::filesystem::path(dir) / row.name;
      sequences.push_back({std::move(row), folder});
    }
  }
  std::printf("collected     %zu sequences from %zu folders\n", sequences.size(), args.positional().size());
  return WriteBatchResults(out, std::move(sequences));
}

}  // namespace

int RunBatch(const std::vector<std::string>& argv) {
  const Args args(argv, kBatchFlags, kBatchSwitches, {"set"});
  if (args.help()) {
    std::fputs(kBatchUsage, stdout);
    return 0;
  }
  const std::filesystem::path out = args.get_or("out", "flatslam-batch");
  if (args.has("collect")) return Collect(args, out);
  if (args.positional().empty()) throw UsageError{"expected at least one INPUT"};

  SequenceSpec defaults;
  if (auto s = args.get("sensor")) defaults.sensor = ParseSensor(*s);
  if (auto s = args.get("settings")) defaults.settings = std::filesystem::absolute(*s).string();
  if (auto c = args.get("config")) defaults.config = std::filesystem::absolute(*c).string();
  if (auto s = args.get("set")) defaults.set.push_back(*s);
  const int64_t max_frames = args.get_int("max-frames", 0);
  if (max_frames < 0) throw UsageError{"--max-frames must be at least 1"};
  defaults.max_frames = static_cast<size_t>(max_frames);
  defaults.seed = static_cast<uint64_t>(args.get_int("seed", 1));
  if (args.has("keep-camera")) defaults.keep_camera = true;
  if (auto m = args.get("camera-from")) {
    if (args.has("keep-camera")) throw UsageError{"--camera-from and --keep-camera: choose one camera"};
    defaults.camera_from = std::filesystem::absolute(*m).string();
  }
  std::vector<SequenceSpec> all = ExpandBatchInputs(args.positional(), defaults);

  std::vector<size_t> positions(all.size());
  for (size_t i = 0; i < all.size(); ++i) positions[i] = i;
  std::string shard_note;
  if (auto s = args.get("shard")) {
    const auto [index, count] = ParseShard(*s);
    positions = ShardPositions(all.size(), index, count);
    shard_note = " (shard " + *s + " of " + std::to_string(all.size()) + " inputs)";
  }
  std::vector<SequenceSpec> specs;
  for (size_t p : positions) specs.push_back(all[p]);

  BatchOptions batch;
  const int64_t jobs = args.get_int("jobs", 0);
  if (jobs < 0) throw UsageError{"--jobs must be at least 1"};
  batch.jobs = static_cast<size_t>(jobs);
  if (auto m = args.get("memory")) batch.memory_mib = ParseBytesMiB(*m);
  batch.deterministic = args.has("deterministic");
  batch.out_dir = out;
  std::filesystem::create_directories(out);

  // One vocabulary for every sequence: memory-mapped once, shared read-only.
  Vocabulary vocabulary;
  const std::string vocabulary_arg = args.get_or("vocabulary", "");
  if (vocabulary_arg != "none") {
    vocabulary =
        Vocabulary::Load(vocabulary_arg.empty() ? DefaultVocabularyPath() : std::filesystem::path(vocabulary_arg));
    batch.vocabulary = &vocabulary;
  }
  std::printf("batch         %zu sequences%s, into %s\n", specs.size(), shard_note.c_str(), out.c_str());
  std::fflush(stdout);

  const bool quiet = args.has("quiet");
  const bool terminal = isatty(STDERR_FILENO) != 0;
  TerminalProgress drawn;
  double last_plain = -1e9;
  batch.on_progress = [&](const BatchProgress& p) {
    if (quiet) return;
    if (terminal) {
      drawn.Draw(p);
    } else if (p.elapsed_s - last_plain >= 10 || p.finished == p.sequences.size()) {
      last_plain = p.elapsed_s;
      std::fprintf(stderr, "%s\n", OverallLine(p).c_str());
    }
  };
  auto message = [&](const std::string& line) {
    if (quiet) return;
    if (terminal)
      drawn.Message(line);
    else
      std::fprintf(stderr, "%s\n", line.c_str());
  };
  batch.on_finished = [&](const SequenceResult& r) {
    message(r.name + ": " + r.status + ", " + std::to_string(r.frames) + " frames, " + std::to_string(r.lost) +
            " lost" + (r.error.empty() ? "" : ": " + r.error));
  };
  batch.on_warning = [&](const std::string& sequence, const std::string& text) {
    message("warning: " + sequence + ": " + text);
  };
  const StopSignals stop_signals("flatslam batch");
  const auto start = std::chrono::steady_clock::now();
  batch.stop = &g_stop;
  std::vector<ReportSequence> sequences;
  for (SequenceResult& r : flatslam::RunBatch(specs, positions, batch)) {
    const std::filesystem::path dir = out / r.name;
    sequences.push_back({std::move(r), dir});
  }
  const int code = WriteBatchResults(out, sequences);
  // How busy the batch kept the machine: the process's CPU time over its wall time and cores.
  const double wall_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  const double cpu_s = usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
                       1e-6 * static_cast<double>(usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
  const double cores = std::max(1u, std::thread::hardware_concurrency());
  size_t frames = 0;
  for (const ReportSequence& s : sequences) frames += s.result.frames;
  std::printf("cpu           %.1f s over %.1f s wall: %.2f of %.0f cores busy (%.0f%%), %.1f ms CPU per frame\n", cpu_s,
              wall_s, cpu_s / wall_s, cores, 100.0 * cpu_s / (wall_s * cores),
              1000.0 * cpu_s / std::max<size_t>(frames, 1));
  std::printf("peak RSS      %.0f MiB (budget %s)\n", PeakRssMiB(),
              batch.memory_mib > 0 ? (std::to_string(std::lround(batch.memory_mib)) + " MiB").c_str()
                                   : "80% of available memory");
  return g_signal != 0 ? 128 + g_signal : code;
}

}  // namespace flatslam::app
