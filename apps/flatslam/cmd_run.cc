// flatslam run: the SLAM pipeline over a dataset, writing trajectories, per-frame stats and a summary.
#include <mimalloc.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <charconv>
#include <chrono>
#include <csignal>
#include <cmath>
#include <cstdlib>
#include <set>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>

#include "args.h"
#include "commands.h"
#include "core/atomic_write.h"
#include "core/error.h"
#include "io/dataset.h"
#include "io/orb_settings.h"
#include "jobs/slam_runner.h"
#include "storage/line_log.h"
#include "storage/snapshot.h"
#include "systems/slam_config.h"
#include "systems/vocabulary.h"
#include "trajectory/metrics.h"
#include "trajectory/trajectory_io.h"

namespace flatslam::app {

const char* const kRunUsage =
    "usage: flatslam run DATASET [--sensor mono|stereo|rgbd] [--out DIR] [--seed N] [--max-frames N]\n"
    "                    [--features N] [--mapping-lag N] [--deterministic] [--quiet]\n"
    "                    [--vocabulary FILE|none] [--no-loop-closing] [--no-global-ba]\n"
    "                    [--skip A:B,...] [--lose-at N,...]\n"
    "                    [--save-map FILE] [--agent N] [--load-map FILE [--localize-only]]\n"
    "                    [--first-frame N] [--config FILE] [--set KEY=VALUE,...] [--list-options]\n"
    "                    [--settings FILE] [--strict] [--checkpoint FILE [--checkpoint-every S]]\n"
    "       flatslam run --resume CHECKPOINT [--quiet]\n\n"
    "Runs SLAM over DATASET (a KITTI/EuRoC/TUM folder, synth:SPEC, or an image folder with --settings)\n"
    "as fast as it can read, and prints a summary: frames, frames lost, keyframes, map points, ms per\n"
    "frame, frames/s, peak RSS, and ATE/RPE when the dataset has ground truth.\n"
    "  --out DIR        write trajectory.tum, trajectory.kitti, keyframes.tum and stats.csv;\n"
    "                   trajectory.tum (poses as tracked) and stats.csv grow as frames are tracked\n"
    "                   (whole lines, flushed at least every second) and trajectory.tum is\n"
    "                   rewritten with the refined poses at the end\n"
    "  --features N     ORB features per image (default: from the camera, see --list-options)\n"
    "  --deterministic  run local mapping inline after each keyframe: same input, same output\n"
    "  --mapping-lag N  keyframes tracking may run ahead of local mapping (default 0: wait for\n"
    "                   it, repeatable); 3 is about 10x faster on monocular KITTI, less accurate,\n"
    "                   and varies from run to run\n"
    "  --max-frames N   stop after N frames\n"
    "  --vocabulary F   bag-of-words vocabulary for relocalization and loop closing (default: the\n"
    "                   one shipped in data/vocabulary, or $FLATSLAM_VOCABULARY); 'none' turns both off\n"
    "  --no-loop-closing  relocalize, but never close loops\n"
    "  --no-global-ba   close loops with the essential graph only (no global bundle adjustment after)\n"
    "  --skip A:B,...   drop frames A..B-1 (the camera seems to jump: a kidnapping test)\n"
    "  --lose-at N,...  declare tracking lost at frame N (a relocalization test)\n"
    "  --load-map FILE  continue a saved map: relocalize in it, then track and extend it\n"
    "  --localize-only  with --load-map: track against the loaded map without changing it\n"
    "  --first-frame N  start at frame N (e.g. continue a session that stopped there)\n"
    "  --agent N        agent id stamped on the map's keyframes (for map merge; default 0)\n"
    "  --save-map FILE  save the final map as a snapshot (see flatslam map); written atomically\n"
    "  --config FILE    SLAM options as 'key = value' lines (# comments); see --list-options\n"
    "  --set K=V,...    set options by name after --config and the flags above\n"
    "  --list-options   print every option with its value for this dataset, in the config format\n"
    "  --settings FILE  an ORB-SLAM2/3 settings YAML: its camera, distortion, baseline and frame rate\n"
    "                   replace the dataset's calibration, its ORBextractor.* and ThDepth set options\n"
    "                   (before --features, --config and --set); needed for a plain image folder\n"
    "  --strict         stop at the first unreadable frame (default: report it, skip it like a\n"
    "                   dropped frame and go on; the summary counts skipped frames)\n"
    "  --checkpoint F   keep an atomic snapshot of the session in F (map, trajectory, options, next\n"
    "                   frame), written in the background every --checkpoint-every seconds (default\n"
    "                   60) and at the end\n"
    "  --resume F       continue the run checkpointed in F: same dataset, options and outputs, from\n"
    "                   the frame after the checkpoint, relocalizing in its map; the trajectory\n"
    "                   covers the frames of both parts\n"
    "Monocular runs initialize from two views; their scale is arbitrary (use Sim(3) ATE).\n"
    "The first SIGINT or SIGTERM stops reading: the frames in flight are tracked, mapping finishes, and\n"
    "the trajectory, stats, summary, map and checkpoint are written as at a normal end; the exit code\n"
    "is then 130 (SIGINT) or 143 (SIGTERM). A second one exits at once; files already in place stay\n"
    "complete (each is replaced atomically).\n";

namespace {

double PeakRssMiB() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;
}

// Memory the allocator has committed now (the heap, without code, stacks and mapped files).
double HeapCommittedMiB() {
  size_t elapsed = 0, user = 0, system = 0, rss = 0, peak_rss = 0, commit = 0, peak_commit = 0, faults = 0;
  mi_process_info(&elapsed, &user, &system, &rss, &peak_rss, &commit, &peak_commit, &faults);
  return static_cast<double>(commit) / (1024.0 * 1024.0);
}

// Resident set size now, from /proc/self/statm (0 where unavailable).
double CurrentRssMiB() {
  std::ifstream statm("/proc/self/statm");
  double size = 0, resident = 0;
  if (!(statm >> size >> resident)) return 0;
  return resident * static_cast<double>(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

// "A:B,C:D" -> {{A, B}, {C, D}}; "N,M" -> {{N, N}, {M, M}} when ranges are not wanted.
std::vector<std::pair<size_t, size_t>> ParseRanges(const std::string& flag, const std::string& text, bool ranges) {
  std::vector<std::pair<size_t, size_t>> out;
  size_t pos = 0;
  while (pos <= text.size()) {
    const size_t comma = std::min(text.find(',', pos), text.size());
    const std::string item = text.substr(pos, comma - pos);
    const size_t colon = item.find(':');
    try {
      if (ranges) {
        if (colon == std::string::npos) throw std::invalid_argument(item);
        size_t used_a = 0, used_b = 0;
        const std::string a = item.substr(0, colon), b = item.substr(colon + 1);
        out.emplace_back(std::stoull(a, &used_a), std::stoull(b, &used_b));
        if (used_a != a.size() || used_b != b.size() || out.back().second <= out.back().first)
          throw std::invalid_argument(item);
      } else {
        size_t used = 0;
        const size_t n = std::stoull(item, &used);
        if (used != item.size()) throw std::invalid_argument(item);
        out.emplace_back(n, n);
      }
    } catch (const std::exception&) {
      throw UsageError{"--" + flag + ": cannot read '" + item + "' (expected " +
                       (ranges ? "A:B with A < B" : "a frame number") + ")"};
    }
    pos = comma + 1;
  }
  return out;
}

// Per-frame times of a session of any length in fixed memory: log-spaced bins 1% apart from
// 1 us to 100 s give the median within 1%; mean and maximum are exact.
class TimeStats {
 public:
  void Add(double ms) {
    const double clamped = std::clamp(ms, kMinMs, kMaxMs);
    ++bins_[static_cast<size_t>(std::log(clamped / kMinMs) / std::log(kStep))];
    ++count_;
    sum_ += ms;
    max_ = std::max(max_, ms);
  }
  [[nodiscard]] double Median() const {
    size_t seen = 0;
    for (size_t b = 0; b < bins_.size(); ++b) {
      seen += bins_[b];
      if (2 * seen > count_) return kMinMs * std::pow(kStep, static_cast<double>(b) + 0.5);
    }
    return 0;
  }
  [[nodiscard]] double Mean() const { return count_ == 0 ? 0 : sum_ / static_cast<double>(count_); }
  [[nodiscard]] double Max() const { return max_; }

 private:
  static constexpr double kMinMs = 1e-3, kMaxMs = 1e5, kStep = 1.01;
  std::array<uint32_t, 1900> bins_{};  // log(1e8) / log(1.01) = 1852 bins
  size_t count_ = 0;
  double sum_ = 0, max_ = 0;
};

// Flags of `flatslam run` that take a value, and switches.
const std::set<std::string> kRunFlags = {
    "sensor",      "out",    "seed",    "max-frames", "features",   "mapping-lag",
    "vocabulary",  "skip",   "lose-at", "save-map",   "agent",      "load-map",
    "first-frame", "config", "set",     "settings",   "checkpoint", "checkpoint-every",
    "resume"};
const std::set<std::string> kRunSwitches = {"deterministic", "quiet",        "no-loop-closing", "no-global-ba",
                                            "localize-only", "list-options", "strict"};

// The run's command line as a checkpoint keeps it for --resume: one "--name=value" per flag,
// paths made absolute (a resume may start elsewhere), without --load-map and --first-frame (the
// checkpoint's map and next frame replace them) and without --resume itself.
std::vector<std::string> ResumableArguments(const std::vector<std::string>& argv) {
  static const std::set<std::string> kPaths = {"out", "save-map", "config", "settings", "vocabulary", "checkpoint"};
  static const std::set<std::string> kReplaced = {"load-map", "first-frame", "resume"};
  auto absolute = [](const std::string& path) { return std::filesystem::absolute(path).lexically_normal().string(); };
  std::vector<std::string> out;
  for (size_t i = 0; i < argv.size(); ++i) {
    const std::string& a = argv[i];
    if (a.size() > 2 && a.rfind("--", 0) == 0) {
      std::string name = a.substr(2), value;
      const size_t eq = name.find('=');
      const bool has_value = eq != std::string::npos || kRunFlags.count(name);
      if (eq != std::string::npos) {
        value = name.substr(eq + 1);
        name = name.substr(0, eq);
      } else if (has_value && i + 1 < argv.size()) {
        value = argv[++i];
      }
      if (kReplaced.count(name)) continue;
      if (kPaths.count(name) && !(name == "vocabulary" && value == "none")) value = absolute(value);
      out.push_back("--" + name + (has_value ? "=" + value : ""));
    } else {
      out.push_back(a.rfind("synth:", 0) == 0 ? a : absolute(a));
    }
  }
  return out;
}

// Signals: the first SIGINT/SIGTERM asks the run to stop; a second one ends the process at once.
std::atomic<bool> g_stop{false};
volatile std::sig_atomic_t g_signal = 0;

extern "C" void OnStopSignal(int signal) {
  if (g_signal != 0) {
    constexpr char kNow[] = "\nflatslam run: second interrupt: exiting now\n";
    (void)!::write(STDERR_FILENO, kNow, sizeof(kNow) - 1);
    ::_exit(128 + signal);
  }
  g_signal = signal;
  g_stop.store(true);
  constexpr char kStopping[] =
      "\nflatslam run: interrupted: finishing the frames in flight, then writing the results (interrupt again "
      "to quit at once)\n";
  (void)!::write(STDERR_FILENO, kStopping, sizeof(kStopping) - 1);
}

// Installs OnStopSignal for SIGINT and SIGTERM while it lives; restores the previous handlers.
class StopSignals {
 public:
  StopSignals() {
    g_stop = false;
    g_signal = 0;
    struct sigaction action {};
    action.sa_handler = OnStopSignal;
    sigemptyset(&action.sa_mask);
    ::sigaction(SIGINT, &action, &old_int_);
    ::sigaction(SIGTERM, &action, &old_term_);
  }
  ~StopSignals() {
    ::sigaction(SIGINT, &old_int_, nullptr);
    ::sigaction(SIGTERM, &old_term_, nullptr);
  }
  StopSignals(const StopSignals&) = delete;
  StopSignals& operator=(const StopSignals&) = delete;

 private:
  struct sigaction old_int_ {
  }, old_term_{};
};

// Test hook: FLATSLAM_INJECT_FAULT=global-ba|loop-closing|checkpoint makes that background work
// throw, so tests can check that its failure becomes a warning and the session goes on.
std::string InjectedFaultName() {
  const char* fault = std::getenv("FLATSLAM_INJECT_FAULT");
  return fault ? fault : "";
}

// stats.csv lines of frames before `next_frame` (a resumed run keeps the first part's lines).
std::string StatsBefore(const std::filesystem::path& path, size_t next_frame, const std::string& header) {
  std::ifstream in(path);
  std::string out = header, line;
  if (!in) return out;
  std::getline(in, line);  // header
  while (std::getline(in, line)) {
    if (in.eof()) break;  // a last line without its newline is incomplete
    size_t frame = 0;
    const auto [ptr, ec] = std::from_chars(line.data(), line.data() + line.size(), frame);
    if (ec != std::errc() || *ptr != ',' || frame >= next_frame) continue;
    out += line + "\n";
  }
  return out;
}

}  // namespace

int RunRun(const std::vector<std::string>& original_argv) {
  // --resume: the checkpoint's own command line, with its map and next frame.
  std::vector<std::string> argv = original_argv;
  std::optional<std::filesystem::path> resume_file;
  std::optional<SnapshotSession> resume_session;
  {
    const Args first(original_argv, kRunFlags, kRunSwitches);
    if (auto r = first.get("resume")) {
      for (const std::string& a : original_argv)
        if (a.rfind("--", 0) == 0 && a != "--quiet" && a.rfind("--resume", 0) != 0)
          throw UsageError{"--resume takes no other option than --quiet (the checkpoint holds the run's own): " + a};
      if (!first.positional().empty() && !(first.positional().size() == 1 && first.positional()[0] == *r))
        throw UsageError{"--resume takes no DATASET (the checkpoint names it)"};
      resume_file = *r;
      const auto session = MapSnapshotView::Open(*resume_file).session_summary();
      FLATSLAM_CHECK(session.has_value(), "--resume ", *resume_file,
                     ": a map snapshot without a session (not written by --checkpoint); continue it with --load-map");
      argv = session->arguments;
      if (first.has("quiet")) argv.push_back("--quiet");
    }
  }
  const Args args(argv, kRunFlags, kRunSwitches);
  if (args.help()) {
    std::fputs(kRunUsage, stdout);
    return 0;
  }
  if (args.positional().size() != 1) throw UsageError{"expected exactly one DATASET"};
  DatasetOptions dataset_options;
  if (auto s = args.get("sensor")) dataset_options.sensor = ParseSensor(*s);
  dataset_options.seed = static_cast<uint64_t>(args.get_int("seed", 1));
  const std::optional<std::string> settings_file = args.get("settings");
  if (settings_file) dataset_options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(*settings_file));
  const auto dataset = OpenDataset(args.positional()[0], dataset_options);
  if (settings_file && DetectDatasetLayout(args.positional()[0], true) != DatasetLayout::kImageFolder)
    std::fprintf(stderr, "settings %s replaces the dataset's calibration\n", settings_file->c_str());
  FLATSLAM_CHECK(dataset->size() > 0, "dataset ", args.positional()[0], " has no frames");
  const int64_t max_frames = args.get_int("max-frames", static_cast<int64_t>(dataset->size()));
  if (max_frames < 1) throw UsageError{"--max-frames must be at least 1"};
  const size_t frames = std::min(dataset->size(), static_cast<size_t>(max_frames));
  std::optional<std::filesystem::path> out_dir;
  if (auto o = args.get("out")) {
    out_dir = *o;
    std::filesystem::create_directories(*out_dir);
  }

  SlamOptions options;
  // Place recognition: the vocabulary is memory-mapped, so loading it costs milliseconds.
  Vocabulary vocabulary;
  double vocabulary_ms = 0;
  const std::string vocabulary_arg = args.get_or("vocabulary", "");
  if (vocabulary_arg != "none") {
    const std::filesystem::path path =
        vocabulary_arg.empty() ? DefaultVocabularyPath() : std::filesystem::path(vocabulary_arg);
    const auto load_start = std::chrono::steady_clock::now();
    vocabulary = Vocabulary::Load(path);
    vocabulary_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - load_start).count();
    options.vocabulary = &vocabulary;
  }
  options.loop_closing = !args.has("no-loop-closing");
  options.global_bundle_adjustment = !args.has("no-global-ba");
  options.localization_only = args.has("localize-only");
  if (options.localization_only && !args.has("load-map") && !resume_file)
    throw UsageError{"--localize-only needs --load-map"};
  if (args.has("checkpoint") && !options.vocabulary)
    throw UsageError{"--checkpoint needs a vocabulary (a resumed run relocalizes in the checkpoint's map)"};
  // A saved map to continue (--load-map, or the checkpoint of --resume): same camera, same vocabulary.
  std::optional<Map> loaded_map;
  std::string loaded_note;
  const std::optional<std::string> map_to_load =
      resume_file ? std::optional<std::string>(resume_file->string()) : args.get("load-map");
  if (const auto& m = map_to_load) {
    const char* flag = resume_file ? "--resume " : "--load-map ";
    FLATSLAM_CHECK(options.vocabulary, flag, *m, ": continuing a map needs a vocabulary (not 'none')");
    SnapshotReadOptions read;
    read.vocabulary_checksum = options.vocabulary->checksum();
    LoadedSnapshot snapshot = LoadMapSnapshot(*m, read);
    const Calibration& have = snapshot.metadata.calibration;
    const Calibration& want = dataset->calibration();
    const bool same_camera = have.sensor == want.sensor && have.camera.width == want.camera.width &&
                             have.camera.height == want.camera.height &&
                             std::abs(have.camera.fx - want.camera.fx) < 1e-6 * want.camera.fx &&
                             std::abs(have.camera.fy - want.camera.fy) < 1e-6 * want.camera.fy &&
                             std::abs(have.camera.cx - want.camera.cx) < 1e-6 * want.camera.fx &&
                             std::abs(have.camera.cy - want.camera.cy) < 1e-6 * want.camera.fy &&
                             std::abs(have.baseline_m - want.baseline_m) < 1e-9 + 1e-6 * want.baseline_m;
    FLATSLAM_CHECK(same_camera, flag, *m, ": the map was built with another camera or sensor than ",
                   args.positional()[0]);
    FLATSLAM_CHECK(!snapshot.maps.empty(), flag, *m, ": the snapshot holds no map");
    size_t best = 0;
    for (size_t k = 1; k < snapshot.maps.size(); ++k)
      if (snapshot.maps[k].map.keyframes().size() > snapshot.maps[best].map.keyframes().size()) best = k;
    if (resume_file) {
      best = snapshot.metadata.session->map;
      resume_session = std::move(*snapshot.metadata.session);
    }
    char note[256];
    std::snprintf(note, sizeof(note), "%s: map %u of %zu, %zu keyframes, %zu map points", m->c_str(),
                  snapshot.maps[best].id, snapshot.maps.size(), snapshot.maps[best].map.keyframes().size(),
                  snapshot.maps[best].map.points().size());
    loaded_note = note;
    loaded_map = std::move(snapshot.maps[best].map);
  }
  const int64_t agent = args.get_int("agent", 0);
  if (agent < 0 || agent > 0xffff) throw UsageError{"--agent must be in [0, 65535]"};
  options.agent = static_cast<uint32_t>(agent);
  if (settings_file)
    for (const auto& [key, value] : SettingsSlamOptions(*dataset_options.settings, dataset->calibration().sensor))
      SetSlamOption(&options, key, value, *settings_file);
  options.orb.features = static_cast<int>(args.get_int("features", options.orb.features));
  options.seed = dataset_options.seed;
  if (auto config = args.get("config")) LoadSlamConfig(*config, &options);
  if (auto settings = args.get("set")) {
    for (size_t pos = 0; pos <= settings->size();) {
      const size_t comma = std::min(settings->find(',', pos), settings->size());
      ApplySlamSetting(&options, std::string_view(*settings).substr(pos, comma - pos));
      pos = comma + 1;
    }
  }
  if (args.has("list-options")) {
    std::vector<DerivedOption> derived;
    const SlamOptions resolved = ResolvedOptions(options, dataset->calibration(), &derived);
    for (const std::string& line : DescribeSlamOptions(resolved, derived)) std::printf("%s\n", line.c_str());
    return 0;
  }
  const bool quiet = args.has("quiet") || !isatty(STDERR_FILENO);
  const std::string fault = InjectedFaultName();
  if (fault == "global-ba") options.inject_fault = InjectedFault::kGlobalBundleAdjustment;
  if (fault == "loop-closing") options.inject_fault = InjectedFault::kLoopClosing;
  SlamRunOptions run;
  run.max_frames = frames;
  run.deterministic = args.has("deterministic");
  run.strict = args.has("strict");
  run.keep_results_on_error = true;  // an error ends the run, but what it computed is still written
  run.max_mapping_lag = static_cast<int>(args.get_int("mapping-lag", run.max_mapping_lag));
  if (run.max_mapping_lag < 0) throw UsageError{"--mapping-lag must be at least 0"};
  const int64_t first_frame = args.get_int("first-frame", 0);
  if (first_frame < 0 || static_cast<size_t>(first_frame) >= frames)
    throw UsageError{"--first-frame must be a frame of the dataset (0.." + std::to_string(frames - 1) + ")"};
  run.first_frame = static_cast<size_t>(first_frame);
  if (resume_session) {
    run.first_frame = std::min<size_t>(resume_session->next_frame, frames);
    run.initial_frames = resume_session->frames;
    char note[160];
    std::snprintf(note, sizeof(note), ", %zu frames tracked before, resuming at frame %zu",
                  resume_session->frames.size(), run.first_frame);
    loaded_note += note;
  }
  if (loaded_map) run.initial_map = &*loaded_map;
  if (auto skip = args.get("skip")) run.skip = ParseRanges("skip", *skip, true);
  if (auto lose = args.get("lose-at"))
    for (const auto& [n, unused] : ParseRanges("lose-at", *lose, false)) run.lose_at.push_back(n);
  SnapshotMetadata metadata;
  metadata.calibration = dataset->calibration();
  metadata.scales = MapScales{options.orb.scale_factor, options.orb.levels};
  // Identity of the vocabulary the map's keyframes were indexed with (0: none).
  metadata.vocabulary_checksum = options.vocabulary ? options.vocabulary->checksum() : 0;
  if (dataset->calibration().sensor == Sensor::kRgbd)
    metadata.rgbd_virtual_baseline_m = options.rgbd_virtual_baseline_m;
  // The map is saved when every stage has drained; a failed save is reported after the summary.
  std::optional<std::filesystem::path> save_map;
  std::string save_error;
  double save_ms = 0;
  auto check_directory = [](const char* flag, const std::filesystem::path& file) {
    const std::filesystem::path dir = file.has_parent_path() ? file.parent_path() : ".";
    FLATSLAM_CHECK(std::filesystem::is_directory(dir), flag, " ", file, ": directory ", dir, " does not exist");
  };
  if (auto m = args.get("save-map")) {
    save_map = *m;
    check_directory("--save-map", *save_map);
    run.on_finished = [&](const Slam& slam) {
      const auto start = std::chrono::steady_clock::now();
      try {
        const SnapshotMapRef ref{0, &slam.map()};
        SaveMapSnapshot(*save_map, {&ref, 1}, metadata);
      } catch (const Error& e) {
        save_error = e.what();
      }
      save_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
    };
  }
  // Checkpoints: the session's map, trajectory, command line and next frame, saved atomically.
  std::optional<std::filesystem::path> checkpoint;
  size_t last_checkpoint_frame = 0;
  if (auto c = args.get("checkpoint")) {
    checkpoint = *c;
    check_directory("--checkpoint", *checkpoint);
    run.checkpoint_every_s = args.get_double("checkpoint-every", 60);
    if (!(run.checkpoint_every_s > 0)) throw UsageError{"--checkpoint-every must be a positive number of seconds"};
    const std::vector<std::string> arguments = ResumableArguments(argv);
    run.on_checkpoint = [&, arguments, inject = fault == "checkpoint"](const Slam::State& state, size_t next_frame) {
      if (inject) Fail("injected failure in checkpoint write");
      SnapshotMetadata with_session = metadata;
      SnapshotSession session;
      session.next_frame = next_frame;
      session.dataset = args.positional()[0];
      session.arguments = arguments;
      state.AnchoredToMap(&session.frames);
      with_session.session = std::move(session);
      const SnapshotMapRef ref{0, &state.map};
      SaveMapSnapshot(*checkpoint, {&ref, 1}, with_session);
      last_checkpoint_frame = next_frame;
    };
  } else if (args.has("checkpoint-every")) {
    throw UsageError{"--checkpoint-every needs --checkpoint FILE"};
  }
  size_t warnings = 0;
  run.on_warning = [&warnings](const std::string& message) {
    ++warnings;
    std::fprintf(stderr, "\nwarning: %s\n", message.c_str());
  };
  size_t skipped = 0;
  run.on_skipped = [&skipped](size_t index, const std::string& reason) {
    ++skipped;
    std::fprintf(stderr, "\nwarning: frame %zu skipped: %s\n", index, reason.c_str());
  };
  // Per-frame statistics and the trajectory as tracked go to stats.csv and trajectory.tum as
  // frames are tracked (whole lines, flushed at least every second): a session of any length
  // keeps only two timings per frame (for the medians) besides its trajectory, and a killed run
  // leaves both files readable. A resumed run keeps the first part's lines.
  const std::string csv_header =
      "frame,t_ns,state,keyframe,reinitialized,relocalized,features,stereo_points,matches,inliers,extract_ms,"
      "track_ms,rss_mib,heap_mib,map_keyframes,map_points\n";
  std::optional<LineLog> csv, streamed;
  if (out_dir) {
    const std::filesystem::path csv_path = *out_dir / "stats.csv";
    if (resume_session) {
      const std::string kept = StatsBefore(csv_path, run.first_frame, csv_header);
      WriteFileAtomically(csv_path, [&](std::FILE* f) { std::fputs(kept.c_str(), f); });
      csv.emplace(csv_path, "", LineLog::Mode::kAppend);
    } else {
      csv.emplace(csv_path, csv_header);
    }
    std::string prefix = kTumHeader;
    if (resume_session)
      for (const AnchoredFramePose& f : resume_session->frames)
        prefix += FormatTumLine({f.t_ns, f.T_cam_world.isometry().inverse()});
    streamed.emplace(*out_dir / "trajectory.tum", prefix);
  }
  size_t done = 0, keyframes_so_far = 0, lost = 0, not_initialized = 0, relocalized = 0, reinitialized = 0;
  TimeStats track_ms, extract_ms;
  run.keep_reports = false;
  const size_t to_do = frames - run.first_frame;
  run.on_frame = [&](const FrameReport& r) {
    ++done;
    if (!r.skipped) {
      keyframes_so_far += r.keyframe;
      lost += r.state == TrackingState::kLost;
      not_initialized += r.state == TrackingState::kNotInitialized;
      relocalized += r.relocalized;
      reinitialized += r.reinitialized;
      track_ms.Add(r.track_ms);
      extract_ms.Add(r.extract_ms);
    }
    // Resident set and committed heap sampled every frame: long sessions show whether memory
    // stays flat.
    if (csv) {
      char line[512];
      std::snprintf(line, sizeof(line), "%zu,%lld,%s,%d,%d,%d,%d,%d,%d,%d,%g,%g,%g,%g,%zu,%zu\n", r.index,
                    static_cast<long long>(r.t_ns), r.skipped ? "skipped" : TrackingStateName(r.state), r.keyframe,
                    r.reinitialized, r.relocalized, r.features, r.stereo_points, r.matches, r.inliers, r.extract_ms,
                    r.track_ms, CurrentRssMiB(), HeapCommittedMiB(), r.map_keyframes, r.map_points);
      csv->Append(line);
    }
    if (streamed && r.T_world_cam) streamed->Append(FormatTumLine({r.t_ns, *r.T_world_cam}));
    if (!quiet && (done % 10 == 0 || done == to_do))
      std::fprintf(stderr, "\rframe %zu / %zu  %-16s keyframes made: %zu   ", done, to_do,
                   r.skipped ? "skipped" : TrackingStateName(r.state), keyframes_so_far);
  };
  // A checkpoint's rows and poses are on disk before the checkpoint itself.
  run.before_checkpoint = [&] {
    if (csv) csv->Flush();
    if (streamed) streamed->Flush();
  };
  const StopSignals stop_signals;
  run.stop = &g_stop;
  const SlamRunResult result = RunSlam(*dataset, options, run);
  if (!quiet) std::fprintf(stderr, "\n");
  const double wall_s = result.wall_s;
  const Trajectory& trajectory = result.trajectory;
  const Trajectory& keyframes = result.keyframes;
  if (out_dir) {
    csv->Close();
    streamed->Close();
    // The streamed poses as tracked give way to the refined ones (each file replaced atomically).
    if (!trajectory.empty()) {
      WriteTum(*out_dir / "trajectory.tum", trajectory);
      WriteKitti(*out_dir / "trajectory.kitti", trajectory);
      WriteTum(*out_dir / "keyframes.tum", keyframes);
    }
  }

  const double mean_track = track_ms.Mean();
  const double mean_extract = extract_ms.Mean();
  std::printf("dataset       %s\n", dataset->name().c_str());
  {
    const Calibration& c = dataset->calibration();
    const SlamOptions resolved = ResolvedOptions(options, c);
    std::printf("camera        %dx%d, fx %.1f, %.3g Hz%s; %d ORB features per image%s\n", c.camera.width,
                c.camera.height, c.camera.fx, c.frame_rate_hz,
                c.sensor == Sensor::kStereo ? (", baseline " + std::to_string(c.baseline_m) + " m").c_str() : "",
                resolved.orb.features, options.orb.features == 0 ? " (from the camera)" : "");
  }
  std::printf("frames        %zu tracked, %zu lost, %zu before initialization, %zu skipped (unreadable)\n",
              trajectory.size(), lost, not_initialized, result.frames_skipped);
  if (g_signal != 0)
    std::printf("interrupted   by %s after frame %zu of %zu: frames after it were not read\n",
                g_signal == SIGINT ? "SIGINT" : "SIGTERM", result.next_frame == 0 ? 0 : result.next_frame - 1, frames);
  if (options.vocabulary) {
    std::printf(
        "places        vocabulary %zu words (loaded in %.1f ms), %zu relocalizations, %zu new map segments, "
        "%zu loop closures\n",
        vocabulary.word_count(), vocabulary_ms, relocalized, reinitialized, result.loop_closures.size());
    const auto gt = dataset->ground_truth();
    // Position of the ground truth nearest in time (within 50 ms), to tell true loops from false.
    auto true_position = [&](int64_t t_ns) -> std::optional<Eigen::Vector3d> {
      if (!gt || gt->empty()) return std::nullopt;
      const auto it =
          std::lower_bound(gt->begin(), gt->end(), t_ns, [](const TimedPose& p, int64_t t) { return p.t_ns < t; });
      const TimedPose* best = nullptr;
      if (it != gt->end()) best = &*it;
      if (it != gt->begin() && (!best || t_ns - std::prev(it)->t_ns < best->t_ns - t_ns)) best = &*std::prev(it);
      if (!best || std::llabs(best->t_ns - t_ns) > 50'000'000) return std::nullopt;
      return best->T_world_cam.translation();
    };
    for (const LoopClosure& l : result.loop_closures) {
      std::printf("  loop        frame %zu -> frame %zu: %d points, scale %.4f, moved %.3f m, %.0f ms", l.frame_index,
                  l.matched_frame_index, l.matches, l.scale, l.correction_m, l.correction_ms);
      const auto a = true_position(l.t_ns), b = true_position(l.matched_t_ns);
      if (a && b) std::printf(", true centres %.2f m apart", (*a - *b).norm());
      std::printf("\n");
    }
  } else {
    std::printf("places        no vocabulary: %zu new map segments after tracking loss\n", reinitialized);
  }
  if (!loaded_note.empty())
    std::printf("continued     %s%s\n", loaded_note.c_str(), options.localization_only ? " (localization only)" : "");
  std::printf("map           %zu keyframes, %zu map points\n", result.keyframe_count, result.point_count);
  std::printf("time          extract median %.1f ms (mean %.1f), track median %.1f ms (mean %.1f) per frame\n",
              extract_ms.Median(), mean_extract, track_ms.Median(), mean_track);
  if (const MappingTimes& m = result.mapping; m.keyframes > 0) {
    const double n = static_cast<double>(m.keyframes);
    std::printf(
        "mapping       %zu keyframes mapped, ms per keyframe: prepare %.1f, triangulate %.1f, fuse %.1f, "
        "local BA %.1f (%zu ended early), cull %.1f, places %.1f\n",
        m.keyframes, m.prepare_ms / n, m.triangulate_ms / n, m.fuse_ms / n, m.local_ba_ms / n, m.local_ba_stopped_early,
        m.cull_ms / n, m.place_ms / n);
  }
  std::printf("throughput    %.1f frames/s end to end (%.2f s wall, reading included)\n", result.frames / wall_s,
              wall_s);
  if (checkpoint) {
    const auto& during = result.frame_ms_during_checkpoints;
    const double longest = during.empty() ? 0 : *std::max_element(during.begin(), during.end());
    TimeStats capture;
    for (double ms : result.checkpoint_capture_ms) capture.Add(ms);
    std::printf(
        "checkpoints   %zu written to %s (last: next frame %zu), %zu failed; copy median %.1f ms (max %.1f); "
        "longest frame while checkpointing %.1f ms; all frames: median %.1f ms, longest %.1f ms\n",
        result.checkpoints, checkpoint->c_str(), last_checkpoint_frame, result.checkpoint_failures, capture.Median(),
        capture.Max(), longest, track_ms.Median(), track_ms.Max());
  }
  if (warnings > 0) std::printf("warnings      %zu (background work that failed; see stderr)\n", warnings);
  std::printf("peak RSS      %.0f MiB\n", PeakRssMiB());
  if (auto gt = dataset->ground_truth(); gt && !trajectory.empty()) {
    EvalOptions eval;
    eval.alignment = Alignment::kSE3;
    const EvalResult se3 = Evaluate(*gt, trajectory, eval);
    eval.alignment = Alignment::kSim3;
    const EvalResult sim3 = Evaluate(*gt, trajectory, eval);
    // The path over the time the trajectory covers (an interrupted run covers a part).
    double length = 0;
    for (size_t i = 1; i < gt->size(); ++i)
      if ((*gt)[i - 1].t_ns >= trajectory.front().t_ns && (*gt)[i].t_ns <= trajectory.back().t_ns)
        length += ((*gt)[i].T_world_cam.translation() - (*gt)[i - 1].T_world_cam.translation()).norm();
    std::printf(
        "ATE           %.4f m RMSE after SE(3) (%zu poses, %.2f%% of the %.1f m path); Sim(3) %.4f m, scale %.4f\n",
        se3.ate_m.rmse, se3.pairs.size(), 100.0 * se3.ate_m.rmse / std::max(length, 1e-9), length, sim3.ate_m.rmse,
        sim3.alignment.scale);
    std::printf("RPE           %.4f m / %.3f deg per frame (RMSE)\n", se3.rpe_frames.translation_m.rmse,
                se3.rpe_frames.rotation_deg.rmse);
  }
  if (!result.error.empty())
    std::printf("stopped       after frame %zu by an error (results cover the frames before): %s\n",
                result.next_frame == 0 ? 0 : result.next_frame - 1, result.error.c_str());
  const int exit_code = g_signal != 0 ? 128 + g_signal : (result.error.empty() ? 0 : 1);
  if (trajectory.empty()) {
    std::printf("result        no frame was tracked: the map never initialized (see stats.csv)\n");
    return exit_code != 0 ? exit_code : 1;
  }
  if (out_dir)
    std::printf("wrote         %s/{trajectory.tum,trajectory.kitti,keyframes.tum,stats.csv}\n", out_dir->c_str());
  if (save_map) {
    if (!save_error.empty()) {
      std::printf("map snapshot  not saved: %s\n", save_error.c_str());
      return exit_code != 0 ? exit_code : 1;
    }
    std::printf("map snapshot  %s (%.2f MiB, saved in %.1f ms)\n", save_map->c_str(),
                std::filesystem::file_size(*save_map) / 1048576.0, save_ms);
  }
  return exit_code;
}

}  // namespace flatslam::app
