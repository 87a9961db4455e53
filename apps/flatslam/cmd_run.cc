// flatslam run: the SLAM pipeline over a dataset, writing trajectories, per-frame stats and a summary.
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
#include <random>

#include "args.h"
#include "commands.h"
#include "core/clock.h"
#include "live.h"
#include "stop_signals.h"
#include "core/atomic_write.h"
#include "core/error.h"
#include "io/dataset.h"
#include "io/orb_settings.h"
#include "jobs/map_camera.h"
#include "jobs/sequence_run.h"
#include "jobs/slam_runner.h"
#include "mapping/rig_check.h"
#include "storage/snapshot.h"
#include "config/slam_config.h"
#include "place/vocabulary.h"
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
    "                    [--settings FILE] [--keep-camera | --camera-from MAP] [--strict]\n"
    "                    [--checkpoint FILE [--checkpoint-every S]]\n"
    "                    [--publish [--dds-domain D] [--dds-peers IP,...|multicast] [--wait-for-server S]]\n"
    "       flatslam run --resume CHECKPOINT [--quiet]\n\n"
    "Runs SLAM over DATASET (a KITTI/EuRoC/TUM folder, synth:SPEC, or an image folder with --settings)\n"
    "as fast as it can read, and prints a summary: frames, frames lost, keyframes, map points, ms per\n"
    "frame, frames/s, peak RSS, and ATE/RPE when the dataset has ground truth.\n"
    "  --out DIR        write trajectory.tum, trajectory.kitti, keyframes.tum and stats.csv, and\n"
    "                   groundtruth.tum, results.csv (the run's row, as flatslam batch writes it) and\n"
    "                   report.html (plots against ground truth; open it in a browser, offline);\n"
    "                   trajectory.tum (poses as tracked) and stats.csv grow as frames are tracked\n"
    "                   (whole lines, flushed at least every second) and trajectory.tum is\n"
    "                   rewritten with the refined poses at the end\n"
    "  --features N     ORB features per image (default: from the camera, see --list-options)\n"
    "  --deterministic  run global bundle adjustment (after a loop closure) inline too, where it\n"
    "                   otherwise runs beside tracking: same input, same output\n"
    "  --mapping-lag N  keyframes tracking may run ahead of local mapping (default 0: wait for\n"
    "                   it, repeatable); 3 is about 1.2x faster on monocular KITTI, less accurate,\n"
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
    "  --set K=V,...    set options by name after --config and the flags above (may repeat)\n"
    "  --list-options   print every option with its value for this dataset, in the config format\n"
    "  --settings FILE  an ORB-SLAM2/3 settings YAML: its camera, distortion, baseline and frame rate\n"
    "                   replace the dataset's calibration, its ORBextractor.* and ThDepth set options\n"
    "                   (before --features, --config and --set); needed for a plain image folder\n"
    "  --keep-camera    monocular: run with the camera as given. By default a monocular run checks\n"
    "                   the camera model against its own map while it is young (as flatslam map\n"
    "                   calibrate does: focal length and a radial k1) and, when the map disagrees\n"
    "                   with it, starts over with the refined camera: a monocular map's scale\n"
    "                   through turns follows small errors of the camera model. After the last\n"
    "                   frame it checks the whole map once more (a young map cannot always tell:\n"
    "                   a straight start, turns later) and, when that disagrees, moves the map's\n"
    "                   keypoints into the refined camera and adjusts the map in it; the\n"
    "                   trajectory, saved map and checkpoint follow\n"
    "  --camera-from MAP  monocular: run with the camera a saved map's session ran with (refined\n"
    "                   from its map, or as given), not checked: sessions of one camera then share\n"
    "                   it, and their maps merge (flatslam map merge)\n"
    "  --strict         stop at the first unreadable frame (default: report it, skip it like a\n"
    "                   dropped frame and go on; the summary counts skipped frames)\n"
    "  --checkpoint F   keep an atomic snapshot of the session in F (map, trajectory, options, next\n"
    "                   frame), written in the background every --checkpoint-every seconds (default\n"
    "                   60) and at the end\n"
    "  --resume F       continue the run checkpointed in F: same dataset, options and outputs, from\n"
    "                   the frame after the checkpoint, relocalizing in its map; the trajectory\n"
    "                   covers the frames of both parts\n"
    "  --publish        a live agent on DDS (what flatslam agent runs): each frame's pose as a ROS 2\n"
    "                   geometry_msgs/PoseStamped on rt/flatslam/agent_N/pose (N = --agent; best\n"
    "                   effort), each mapped keyframe on flatslam/keyframes for flatslam server\n"
    "                   (reliable; kept for a server that starts later); --dds-domain D (default 0),\n"
    "                   --dds-peers: hosts found by unicast discovery (default 127.0.0.1) or\n"
    "                   'multicast' for DDS's default discovery. Once the server's corrections\n"
    "                   place the agent in a merged map, the agent moves its map into that map's\n"
    "                   frame (a monocular one to its scale; its saved trajectory and map follow);\n"
    "                   --own-frame keeps it in its own frame (published poses are corrected\n"
    "                   either way). A run that no server has matched by its end ends unheard\n"
    "                   (a warning says so); --wait-for-server S first waits up to S seconds for\n"
    "                   one (default 0), then sends it the whole map\n"
    "Monocular runs initialize from two views; their scale is arbitrary (use Sim(3) ATE).\n"
    "The first SIGINT or SIGTERM stops reading: the frames in flight are tracked, mapping finishes, and\n"
    "the trajectory, stats, summary, map and checkpoint are written as at a normal end; the exit code\n"
    "is then 130 (SIGINT) or 143 (SIGTERM). A second one exits at once; files already in place stay\n"
    "complete (each is replaced atomically).\n";

namespace {

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

// Flags of `flatslam run` that take a value, and switches.
const std::set<std::string> kRunFlags = {
    "sensor",      "out",        "seed",      "max-frames", "features",   "mapping-lag",
    "vocabulary",  "skip",       "lose-at",   "save-map",   "agent",      "load-map",
    "first-frame", "config",     "set",       "settings",   "checkpoint", "checkpoint-every",
    "resume",      "dds-domain", "dds-peers", "run-id",     "wait-for-server", "camera-from"};
const std::set<std::string> kRunSwitches = {"deterministic", "quiet",         "no-loop-closing",
                                            "no-global-ba",  "localize-only", "list-options",
                                            "strict",        "publish",       "own-frame",
                                            "keep-camera"};

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

// Test hook: FLATSLAM_INJECT_FAULT=global-ba|loop-closing|checkpoint makes that background work
// throw, so tests can check that its failure becomes a warning and the session goes on.
std::string InjectedFaultName() {
  const char* fault = std::getenv("FLATSLAM_INJECT_FAULT");
  return fault ? fault : "";
}

// What a run that lost frames prints under its frame counts: how much was lost, what the new
// map segments mean for the ATE, how tracking ended before each loss (fading inliers or an
// abrupt break, measured), and what to look at. Empty when nothing was lost.
std::string DescribeLosses(const RunRecorder::Counts& counts, const Calibration& calibration,
                           const SlamOptions& resolved) {
  if (counts.lost == 0 && counts.reinitialized == 0) return "";
  const bool monocular = calibration.sensor == Sensor::kMonocular;
  const size_t given = counts.frames;
  char text[1024];
  std::string out;
  if (counts.lost > 0) {
    std::snprintf(text, sizeof(text), "warning       %zu of %zu frames lost (%.1f%%) in %zu stretch%s", counts.lost,
                  given, 100.0 * static_cast<double>(counts.lost) / static_cast<double>(std::max<size_t>(given, 1)),
                  counts.lost_stretches, counts.lost_stretches == 1 ? "" : "es");
  } else {
    std::snprintf(text, sizeof(text), "warning       no frame lost, but tracking failed");
  }
  out += text;
  if (counts.reinitialized > 0) {
    std::snprintf(text, sizeof(text), "; %zu new map segment%s started%s", counts.reinitialized,
                  counts.reinitialized == 1 ? "" : "s",
                  monocular ? " (a monocular segment keeps a scale of its own until a loop closure joins it to the "
                              "map: one alignment of the whole trajectory, as the ATE below, does not measure it)"
                            : " (each placed where the last pose was predicted)");
    out += text;
  }
  out += "\n";
  bool faded = false;
  if (!counts.inliers_before_loss.empty()) {
    std::vector<int> inliers = counts.inliers_before_loss;
    std::nth_element(inliers.begin(), inliers.begin() + inliers.size() / 2, inliers.end());
    const int median = inliers[inliers.size() / 2];
    // Under twice the floor, tracking thinned out over frames; above it, one frame broke it.
    faded = median < 2 * resolved.min_local_map_inliers;
    std::snprintf(text, sizeof(text),
                  "              the last frame tracked before a loss kept %d inliers (median; under %d is lost): "
                  "%s\n",
                  median, resolved.min_local_map_inliers,
                  faded ? "tracking faded over the frames before"
                        : "tracking broke at one frame (a fast turn, a view the map has not seen, a bad image)");
    out += text;
  }
  std::snprintf(text, sizeof(text),
                "              check the calibration first; where the view changes much from one frame to the next "
                "(fast motion at %.3g Hz), more keypoints per image may help: --set orb.features=%d (now %d)\n",
                calibration.frame_rate_hz, std::min(2 * resolved.orb.features, kMaxDerivedFeatures),
                resolved.orb.features);
  out += text;
  // A monocular map fades where new points do not come fast enough: the view turns to texture
  // whose rays have not yet diverged by the parallax floor (fast glances, turns, narrow lenses).
  if (monocular && faded && resolved.min_parallax_deg > kDepthParallaxDeg) {
    std::snprintf(text, sizeof(text),
                  "              a monocular map that fades makes too few new points; a lower parallax floor makes "
                  "more, placed less precisely in depth: --set min_parallax_deg=%.3f (now %.3g)\n",
                  kDepthParallaxDeg, resolved.min_parallax_deg);
    out += text;
  }
  return out;
}

// The trajectory's pieces between new map segments, each aligned alone (Sim(3)): what each
// segment's map got right, where one alignment of all of them (a monocular run's segments differ
// in scale) measures none. Nothing without new segments.
void PrintSegmentAccuracy(const Trajectory& gt, const Trajectory& trajectory, const std::vector<int64_t>& starts_t_ns,
                          bool monocular) {
  if (starts_t_ns.empty() || trajectory.empty()) return;
  std::vector<Trajectory> pieces(1);
  size_t next = 0;
  for (const TimedPose& pose : trajectory) {
    while (next < starts_t_ns.size() && pose.t_ns >= starts_t_ns[next]) {
      ++next;
      if (!pieces.back().empty()) pieces.emplace_back();
    }
    pieces.back().push_back(pose);
  }
  std::printf("segments      %zu pieces of the trajectory between new map segments, each aligned alone:\n",
              pieces.size());
  for (const Trajectory& piece : pieces) {
    SequenceResult score;
    if (piece.size() >= 3) ScoreAgainstGroundTruth(gt, piece, &score);
    std::printf("  piece       %zu poses, %.1f-%.1f s", piece.size(),
                1e-9 * (piece.front().t_ns - trajectory.front().t_ns),
                1e-9 * (piece.back().t_ns - trajectory.front().t_ns));
    if (score.ate_sim3_m) {
      std::printf(": ATE Sim(3) %.4f m (%.2f%% of %.1f m), scale %.4f", *score.ate_sim3_m,
                  100.0 * *score.ate_sim3_m / std::max(*score.path_m, 1e-9), *score.path_m, *score.scale);
      if (!monocular) std::printf(", SE(3) %.4f m", *score.ate_se3_m);
    }
    std::printf("\n");
  }
}

}  // namespace

int RunRun(const std::vector<std::string>& original_argv) {
  // --resume: the checkpoint's own command line, with its map and next frame.
  std::vector<std::string> argv = original_argv;
  std::optional<std::filesystem::path> resume_file;
  std::optional<SnapshotSession> resume_session;
  {
    const Args first(original_argv, kRunFlags, kRunSwitches, {"set"});
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
  const Args args(argv, kRunFlags, kRunSwitches, {"set"});
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
  std::unique_ptr<Dataset> dataset = OpenDataset(args.positional()[0], dataset_options);
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
    vocabulary_ms = MsSince(load_start);
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
  CameraRefit continued_refit;
  // The camera as the dataset (and --settings) gives it: what a refinement applies to.
  const PinholeCamera given_camera = dataset->calibration().camera;
  const std::optional<std::string> map_to_load =
      resume_file ? std::optional<std::string>(resume_file->string()) : args.get("load-map");
  if (const auto& m = map_to_load) {
    const char* flag = resume_file ? "--resume " : "--load-map ";
    FLATSLAM_CHECK(options.vocabulary, flag, *m, ": continuing a map needs a vocabulary (not 'none')");
    SnapshotReadOptions read;
    read.vocabulary_checksum = options.vocabulary->checksum();
    LoadedSnapshot snapshot = LoadMapSnapshot(*m, read);
    // A map whose session refined the dataset's camera continues through that camera.
    if (snapshot.metadata.camera_refit.refined() && dataset->calibration().sensor == Sensor::kMonocular)
      dataset = ApplyCameraRefit(std::move(dataset), continued_refit = snapshot.metadata.camera_refit);
    FLATSLAM_CHECK(SameCamera(snapshot.metadata.calibration, dataset->calibration()), flag, *m,
                   ": the map was built with another camera or sensor than ", args.positional()[0]);
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
  // Another session's camera: the refinement its map records, applied to this dataset, must give
  // the camera that map was built with (the same camera before refinement). A resumed run's
  // checkpoint already records the camera its session used.
  const std::optional<std::string> camera_from = resume_file ? std::nullopt : args.get("camera-from");
  if (camera_from) {
    if (args.has("keep-camera")) throw UsageError{"--camera-from and --keep-camera: choose one camera"};
    if (map_to_load) throw UsageError{"--camera-from with --load-map: a continued map has its own camera"};
    dataset = DatasetThroughCameraOf(std::move(dataset), *camera_from, &continued_refit);
  }
  const int64_t agent = args.get_int("agent", 0);
  if (agent < 0 || agent > 0xffff) throw UsageError{"--agent must be in [0, 65535]"};
  options.agent = static_cast<uint32_t>(agent);
  options.seed = dataset_options.seed;
  std::vector<std::string> set;
  if (auto settings = args.get("set")) set.push_back(*settings);
  ApplySlamOptionSources(&options, dataset_options.settings.get(), dataset->calibration().sensor,
                         static_cast<int>(args.get_int("features", 0)), args.get_or("config", ""), set);
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
    run.initial_global_adjustment = resume_session->global_adjustment_pending;
    char note[200];
    std::snprintf(
        note, sizeof(note), ", %zu frames tracked before, resuming at frame %zu%s", resume_session->frames.size(),
        run.first_frame,
        resume_session->global_adjustment_pending ? " (its global bundle adjustment after a loop runs again)" : "");
    loaded_note += note;
  }
  if (loaded_map) run.initial_map = &*loaded_map;
  if (auto skip = args.get("skip")) run.skip = ParseRanges("skip", *skip, true);
  if (auto lose = args.get("lose-at"))
    for (const auto& [n, unused] : ParseRanges("lose-at", *lose, false)) run.lose_at.push_back(n);
  SnapshotMetadata metadata;
  metadata.calibration = dataset->calibration();
  metadata.camera_refit = continued_refit;
  if (dataset->calibration().sensor == Sensor::kMonocular) metadata.given_camera = given_camera;
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
    run.on_finished = [&](const SlamSession& slam) {
      const auto start = std::chrono::steady_clock::now();
      try {
        const SnapshotMapRef ref{0, &slam.map()};
        SaveMapSnapshot(*save_map, {&ref, 1}, metadata);
      } catch (const Error& e) {
        save_error = e.what();
      }
      save_ms = MsSince(start);
    };
  }
  // A live agent's run id on the servers, new in every process (a restarted agent's keyframes and
  // points never collide with its earlier run's ids there). Its checkpoints keep it as --run-id:
  // a run resumed from one tells the servers that it replaces that run.
  uint64_t run_id = 0, resumes_run = 0;
  if (args.has("publish")) {
    if (auto previous = args.get("run-id")) {
      if (!resume_file) throw UsageError{"--run-id is kept by --checkpoint for --resume; it is not set by hand"};
      const auto [end, ec] = std::from_chars(previous->data(), previous->data() + previous->size(), resumes_run, 16);
      if (ec != std::errc() || end != previous->data() + previous->size() || resumes_run == 0)
        throw UsageError{"--run-id: expected a run id in hex, got '" + *previous + "'"};
    }
    std::random_device device;
    while (run_id == 0 || run_id == resumes_run) run_id = uint64_t{device()} << 32 ^ device();
    std::erase_if(argv, [](const std::string& a) { return a.rfind("--run-id=", 0) == 0; });
    char id[32];
    std::snprintf(id, sizeof(id), "--run-id=%016llx", static_cast<unsigned long long>(run_id));
    argv.push_back(id);
  } else if (args.has("run-id")) {
    throw UsageError{"--run-id needs --publish"};
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
    run.on_checkpoint = [&, arguments, inject = fault == "checkpoint"](const SlamSession::State& state,
                                                                       size_t next_frame) {
      if (inject) Fail("injected failure in checkpoint write");
      SnapshotMetadata with_session = metadata;
      SnapshotSession session;
      session.next_frame = next_frame;
      session.dataset = args.positional()[0];
      session.arguments = arguments;
      session.global_adjustment_pending = state.global_adjustment_pending;
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
  // frames are tracked: a session of any length keeps only two timings per frame (for the
  // medians) besides its trajectory. A resumed run keeps the first part's lines.
  RunRecorder recorder(out_dir, run.first_frame, resume_session ? &resume_session->frames : nullptr);
  const RunRecorder::Counts& counts = recorder.counts();
  run.keep_reports = false;
  const size_t to_do = frames - run.first_frame;
  std::unique_ptr<AgentPublisher> link;
  if (args.has("publish")) {
    FLATSLAM_CHECK(g_make_agent_publisher != nullptr, "--publish: this executable has no DDS support (flatslam-live)");
    const double wait_for_server_s = args.get_double("wait-for-server", 0);
    if (wait_for_server_s < 0) throw UsageError{"--wait-for-server must be 0 or a positive number of seconds"};
    link = g_make_agent_publisher(options.agent,
                                  LiveOptions{args.get_or("dds-domain", "0"), args.get_or("dds-peers", "127.0.0.1"),
                                              !args.has("own-frame"), run_id, resumes_run, wait_for_server_s},
                                  AgentCamera{metadata.calibration, metadata.scales, metadata.rgbd_virtual_baseline_m});
    run.on_keyframe_mapped = [&](SlamSession& slam, KeyFrameHandle keyframe) { link->OnKeyFrame(slam, keyframe); };
    run.on_finished = [&, save = run.on_finished](const SlamSession& slam) {
      if (save) save(slam);
      link->PublishFinalMap(slam);
    };
  } else if (args.has("dds-domain") || args.has("dds-peers") || args.has("own-frame") || args.has("wait-for-server")) {
    throw UsageError{"--dds-domain, --dds-peers, --own-frame and --wait-for-server need --publish"};
  }
  run.on_frame = [&](const FrameReport& r) {
    recorder.OnFrame(r);
    if (link) link->OnFrame(r);
    if (!quiet && (counts.frames % 10 == 0 || counts.frames == to_do))
      std::fprintf(stderr, "\rframe %zu / %zu  %-16s keyframes made: %zu   ", counts.frames, to_do,
                   r.skipped ? "skipped" : TrackingStateName(r.state), counts.keyframes);
  };
  // A checkpoint's rows and poses are on disk before the checkpoint itself.
  run.before_checkpoint = [&] { recorder.Flush(); };
  // A live agent's keyframes leave the process as they are made: it keeps the camera it was given.
  run.check_camera = !link && !args.has("keep-camera") && !camera_from;
  run.continued_refit = continued_refit;
  run.continued_given = given_camera;
  run.on_camera_refined = [&](const CameraRefit& refit, const Calibration& refined, bool restart) {
    // Saved maps and checkpoints describe the camera the run uses, and how to see the dataset through it.
    metadata.calibration = refined;
    metadata.camera_refit = refit;
    if (!quiet)
      std::fprintf(stderr, "\rcamera model refined by the map (k1 %+.4f, focal length %+.2f%%): %s\n", refit.k1,
                   100 * (refit.focal_scale - 1), restart ? "starting over" : "the map moves into it");
  };
  const StopSignals stop_signals("flatslam run");
  run.stop = &g_stop;
  const SlamRunResult result = RunSlam(*dataset, options, run);
  if (!quiet) std::fprintf(stderr, "\n");
  const double wall_s = result.wall_s;
  const Trajectory& trajectory = result.trajectory;
  recorder.Finish(result);

  const TimeStats& track_ms = counts.track_ms;
  const TimeStats& extract_ms = counts.extract_ms;
  const double mean_track = track_ms.Mean();
  const double mean_extract = extract_ms.Mean();
  std::printf("dataset       %s\n", dataset->name().c_str());
  const SlamOptions resolved = ResolvedOptions(options, dataset->calibration());
  {
    const Calibration& c = dataset->calibration();
    std::printf("camera        %dx%d, fx %.1f, %.3g Hz%s; %d ORB features per image%s\n", c.camera.width,
                c.camera.height, c.camera.fx, c.frame_rate_hz,
                c.sensor == Sensor::kStereo ? (", baseline " + std::to_string(c.baseline_m) + " m").c_str() : "",
                resolved.orb.features, options.orb.features == 0 ? " (from the camera)" : "");
    if (result.camera_restarts > 0) {
      const CameraRefit& refit = result.camera_refit_tracked;
      const std::string last = DescribeCameraCheck(result.camera_check, result.camera_checked);
      std::printf("camera check  the map of the first %zu frames disagreed with the camera model%s: the run started "
                  "over with k1 %+.4f and the focal length %+.2f%% (undistorted: fx %.2f); --keep-camera keeps "
                  "the given one\n"
                  "              last check, of the camera at fx %.2f: %s\n",
                  result.frames_before_restart,
                  result.camera_restarts > 1 ? " (twice: the first refinement fell short)" : "", refit.k1,
                  100 * (refit.focal_scale - 1), result.camera_tracked.fx, result.camera_checked.fx,
                  last.substr(0, last.find('\n')).c_str());
    } else if (const std::string check = DescribeCameraCheck(result.camera_check, c.camera); !check.empty()) {
      std::printf("camera check  %s\n", check.c_str());
      if (CameraCheckDisagrees(result.camera_check))
        std::printf("              the run kept the given camera: the refined one moves the image's corner by %.1f px, "
                    "outside what a run corrects by itself (1 px to 5%% of the half-diagonal)\n",
                    CameraCheckCornerShiftPx(result.camera_check, c.camera));
    }
    if (const std::string end = DescribeCameraCheck(result.camera_check_at_end, result.camera_tracked); !end.empty()) {
      std::printf("camera check  after the last frame, the whole map (%.0f ms): %s\n", result.camera_end_ms,
                  end.substr(0, end.find('\n')).c_str());
      if (result.camera_refined_at_end)
        std::printf("              it disagreed: its %zu keypoints moved into the refined camera (k1 %+.4f, focal "
                    "length %+.2f%% over the given: fx %.2f; up to %.2f px) and it was adjusted in it; the trajectory "
                    "follows its keyframes\n",
                    result.camera_end_keypoints, result.camera_refit.k1, 100 * (result.camera_refit.focal_scale - 1),
                    result.calibration.camera.fx, result.camera_end_max_shift_px);
    }
  }
  std::printf("frames        %zu tracked, %zu lost, %zu before initialization, %zu skipped (unreadable)\n",
              trajectory.size(), counts.lost, counts.not_initialized, result.frames_skipped);
  std::fputs(DescribeLosses(counts, dataset->calibration(), resolved).c_str(), stdout);
  if (g_signal != 0)
    std::printf("interrupted   by %s after frame %zu of %zu: frames after it were not read\n",
                g_signal == SIGINT ? "SIGINT" : "SIGTERM", result.next_frame == 0 ? 0 : result.next_frame - 1, frames);
  if (options.vocabulary) {
    std::printf(
        "places        vocabulary %zu words (loaded in %.1f ms), %zu relocalizations, %zu new map segments, "
        "%zu loop closures\n",
        vocabulary.word_count(), vocabulary_ms, counts.relocalized, counts.reinitialized, result.loop_closures.size());
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
    std::printf("places        no vocabulary: %zu new map segments after tracking loss\n", counts.reinitialized);
  }
  if (!loaded_note.empty())
    std::printf("continued     %s%s\n", loaded_note.c_str(), options.localization_only ? " (localization only)" : "");
  std::printf("map           %zu keyframes, %zu map points\n", result.keyframe_count, result.point_count);
  if (result.rig.ok)
    std::printf("stereo rig    %s\n", DescribeDisparityOffset(result.rig, options.stereo.disparity_offset_px).c_str());
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
  if (link) {
    // Keyframes a server has not yet acknowledged are lost when the process ends: wait a little.
    const bool delivered = link->Finish(10.0);
    std::printf("published     %s%s\n", link->Summary().c_str(),
                delivered ? "" : " (not every keyframe acknowledged within 10 s)");
    if (link->servers_matched() == 0)
      std::fprintf(stderr,
                   "\nwarning: no server matched this agent, so no server holds its map: start flatslam server "
                   "before the agent ends, check --dds-domain and --dds-peers, or let the agent wait for one at "
                   "its end with --wait-for-server SECONDS\n");
  }
  if (warnings > 0) std::printf("warnings      %zu (background work that failed; see stderr)\n", warnings);
  std::printf("peak RSS      %.0f MiB\n", PeakRssMiB());
  // The run's row of the results table, as `flatslam batch` writes it for each sequence.
  SequenceResult row = ResultOfRun(result, counts);
  if (continued_refit.refined() && !result.camera_refined_at_end) {  // --camera-from's or the continued map's
    row.camera_refit_k1 = continued_refit.k1;
    row.camera_refit_focal_scale = continued_refit.focal_scale;
  }
  row.name = dataset->name();
  row.dataset = args.positional()[0];
  row.sensor = SensorName(dataset->calibration().sensor);
  row.wall_s = wall_s;
  row.peak_rss_mib = PeakRssMiB();
  const std::optional<Trajectory> gt = dataset->ground_truth();
  if (gt) ScoreAgainstGroundTruth(*gt, trajectory, &row);
  if (row.ate_se3_m) {
    std::printf(
        "ATE           %.4f m RMSE after SE(3) (%zu poses, %.2f%% of the %.1f m path); Sim(3) %.4f m, scale %.4f\n",
        *row.ate_se3_m, trajectory.size(), 100.0 * *row.ate_se3_m / std::max(*row.path_m, 1e-9), *row.path_m,
        *row.ate_sim3_m, *row.scale);
    std::printf("RPE           %.4f m / %.3f deg per frame (RMSE)\n", *row.rpe_m, *row.rpe_deg);
    PrintSegmentAccuracy(*gt, trajectory, counts.new_segment_t_ns, dataset->calibration().sensor == Sensor::kMonocular);
  }
  std::string report_error;
  if (out_dir) {
    try {
      WriteSequenceSummary(*out_dir, row, gt);
    } catch (const std::exception& e) {
      report_error = e.what();
    }
  }
  if (!result.error.empty())
    std::printf("stopped       after frame %zu by an error (results cover the frames before): %s\n",
                result.next_frame == 0 ? 0 : result.next_frame - 1, result.error.c_str());
  const int exit_code = g_signal != 0 ? 128 + g_signal : (result.error.empty() ? 0 : 1);
  if (trajectory.empty()) {
    std::printf("result        no frame was tracked: the map never initialized (see stats.csv)\n");
    return exit_code != 0 ? exit_code : 1;
  }
  if (out_dir) {
    std::printf("wrote         %s/{trajectory.tum,trajectory.kitti,keyframes.tum,stats.csv%s}\n", out_dir->c_str(),
                gt ? ",groundtruth.tum" : "");
    if (report_error.empty())
      std::printf("report        %s/report.html (and its row in results.csv)\n", out_dir->c_str());
    else
      std::printf("report        not written: %s\n", report_error.c_str());
  }
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
