// flatslam map: describe, verify, export and merge map snapshots (files written by `run --save-map`).
#include <algorithm>
#include <chrono>
#include <exception>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <string>
#include <system_error>
#include <thread>

#include <tbb/parallel_for.h>

#include "args.h"
#include "merge_and_save.h"
#include "commands.h"
#include "core/atomic_write.h"
#include "core/clock.h"
#include "core/error.h"
#include "jobs/map_camera.h"
#include "storage/colmap_export.h"
#include "storage/snapshot.h"
#include "mapping/camera_check.h"
#include "mapping/rig_check.h"
#include "merge/map_merge.h"
#include "slam/session.h"
#include "place/vocabulary.h"
#include "trajectory/trajectory_io.h"

namespace flatslam::app {

const char* const kMapUsage =
    "usage: flatslam map info FILE\n"
    "       flatslam map verify FILE [--vocabulary-checksum N]\n"
    "       flatslam map export FILE [--ply points.ply] [--ply-format ascii|binary]\n"
    "                               [--trajectory FILE [--format tum|kitti|euroc] [--agent N]]\n"
    "                               [--colmap DIR [--min-track N]]\n"
    "       flatslam map calibrate FILE [--settings-out FILE] [-o OUT]\n"
    "       flatslam map merge A B [C...] -o OUT [--vocabulary FILE] [--min-matches N] [--min-pairs N]\n"
    "                       [--refine] [--close-loops] [--seed N]\n\n"
    "Map snapshots (.fsmap) hold one or more maps with their keyframes, map points and graph edges.\n"
    "  info     format version, file size, vocabulary checksum, calibration, and per map: id,\n"
    "           agents, keyframes, map points, observations, bounding box (read in place: fast)\n"
    "  verify   checks everything: structure, every index, the content hash, that each map\n"
    "           rebuilds consistently; prints 'ok' and exits 0, else the problem and exits 1;\n"
    "           for a stereo map, also how far its disparities sit from its multi-view points\n"
    "           (a rig's rectification error, as `flatslam run` prints it)\n"
    "  export   map points as a PLY point cloud (all maps; ascii by default), the keyframe\n"
    "           trajectory (T_world_cam sorted by time, --format tum (default), kitti (with the\n"
    "           times in FILE.times.txt) or euroc csv; with several maps the poses of each stay\n"
    "           in that map's own frame; --agent N keeps only agent N's keyframes) and/or a\n"
    "           COLMAP model:\n"
    "    --colmap DIR  a COLMAP text model (cameras.txt, images.txt, points3D.txt; DIR is created):\n"
    "                  one PINHOLE camera (the left/colour camera), an image per keyframe (pose\n"
    "                  world-to-camera, its keypoints as POINTS2D), a 3D point per map point with\n"
    "                  observations (grey, its tracks). Image names are <timestamp ns>.png\n"
    "                  (agent<N>/<timestamp ns>.png for maps of several agents): labels, not files\n"
    "                  on disk. A snapshot of several maps gets DIR/<map id>/ per map\n"
    "    --min-track N with --colmap: only points seen by N or more keyframes (default 1: every\n"
    "                  observed point); 2 for COLMAP's bundle_adjuster, which refuses points seen\n"
    "                  once (stereo and RGB-D maps hold points placed from one keyframe's depth)\n"
    "  calibrate  how well the camera model fits the map's own keypoints: keyframes and points\n"
    "           adjusted once more with the focal length (one scale for fx and fy) and a radial\n"
    "           term k1 free (the first two keyframes held); prints both with standard errors and\n"
    "           says whether the keypoints disagree with the model (beyond 5 standard errors).\n"
    "           A monocular map's scale through turns follows small camera errors; a straight\n"
    "           path barely fixes the focal length, and the standard errors say so.\n"
    "           A map made with a wrong model has partly absorbed it (the keyframes and points\n"
    "           bend to fit it): the check sees what is left, so the refined camera moves towards\n"
    "           the truth, not always all the way, and an error the map absorbed goes unseen\n"
    "    --settings-out F  monocular maps: an ORB-SLAM2 settings file with the refined camera,\n"
    "                      for `flatslam run DATASET --settings F`. k1 is a radial term of the\n"
    "                      images as the map saw them (undistorted): the camera as written suits\n"
    "                      datasets whose images are stored undistorted (KITTI, rectified folders);\n"
    "                      where the dataset's calibration has distortion of its own (EuRoC, TUM\n"
    "                      fr1-3), k1 is a residual on top of it, not a replacement\n"
    "    -o OUT        monocular maps: OUT holds the map in the refined camera: every keypoint\n"
    "                  moved from the camera the session saw its images through into the refined\n"
    "                  one, then keyframes and points adjusted in it to convergence, so they shed\n"
    "                  what they had bent to fit the old model (a room seen through a lens its\n"
    "                  calibration leaves out: keyframes' Sim(3) ATE 0.021 -> 0.005 m). OUT\n"
    "                  records the refinement: `run --load-map OUT` sees the dataset through it\n"
    "  merge    joins the maps of several snapshots (same calibration and vocabulary) where they\n"
    "           overlap: place recognition between every pair of maps, a verified SE(3) transform\n"
    "           (Sim(3) for monocular maps) that several keyframe pairs must agree on; the maps\n"
    "           join along the strongest overlaps (a spanning tree of the overlap graph), each\n"
    "           merge fusing duplicate points, spreading the correction over the essential graph\n"
    "           and welding the seam with a bundle adjustment of about 50 keyframes around it;\n"
    "           then a bundle adjustment of each merged map as a whole (two iterations, every\n"
    "           keyframe free: the points a map shares with the others correct its shape).\n"
    "           The first map's frame is kept; maps that overlap nothing are written as separate\n"
    "           maps, each in its own frame. Inputs are never modified; OUT is written atomically.\n"
    "           Monocular sessions of one camera whose runs refined it differently merge too: a\n"
    "           later map's keypoints move into the first map's camera through the camera both\n"
    "           were given, and that map is adjusted alone in it first.\n"
    "    --vocabulary F   the vocabulary the maps were built with (default: the shipped one or\n"
    "                     $FLATSLAM_VOCABULARY); its checksum must match the snapshots'\n"
    "    --min-matches N  map points a keyframe pair must match (default 40)\n"
    "    --min-pairs N    agreeing keyframe pairs, no keyframe used twice, needed to merge (default 3)\n"
    "    --refine         that adjustment runs to convergence (5 robust iterations, outliers\n"
    "                     dropped, 10 more): about 3x its time\n"
    "    --close-loops    then closes loops in each merged map as a SLAM session would: where the\n"
    "                     maps meet again away from the seams, or a map's own loop was never closed\n"
    "                     (a loop search per keyframe: about 0.5 s per 350 keyframes, plus 0.4 s\n"
    "                     per loop closed), then a bundle adjustment of the loops' agents (the\n"
    "                     other agents held), before the adjustment of the whole map\n";

namespace {

int Info(const std::string& file) {
  SnapshotReadOptions options;
  options.verify_content_hash = false;  // structure and indices only: milliseconds on any size
  const auto start = std::chrono::steady_clock::now();
  const MapSnapshotView view = MapSnapshotView::Open(file, options);
  const double open_ms = MsSince(start);
  const Calibration calib = view.calibration();
  std::printf("file          %s\n", file.c_str());
  std::printf("size          %zu bytes (%.2f MiB), opened and verified in %.2f ms\n", view.file_size(),
              view.file_size() / 1048576.0, open_ms);
  std::printf("format        version %u\n", view.format_version());
  std::printf("vocabulary    checksum %016llx%s\n", static_cast<unsigned long long>(view.vocabulary_checksum()),
              view.vocabulary_checksum() == 0 ? " (none)" : "");
  std::printf("sensor        %s, %dx%d, fx %.3f fy %.3f cx %.3f cy %.3f", SensorName(calib.sensor), calib.camera.width,
              calib.camera.height, calib.camera.fx, calib.camera.fy, calib.camera.cx, calib.camera.cy);
  if (calib.sensor == Sensor::kStereo) std::printf(", baseline %.4f m", calib.baseline_m);
  if (calib.sensor == Sensor::kRgbd && view.rgbd_virtual_baseline_m() > 0)
    std::printf(", virtual baseline %.4f m", view.rgbd_virtual_baseline_m());
  if (calib.frame_rate_hz > 0) std::printf(", %.1f Hz", calib.frame_rate_hz);
  std::printf("\nscales        factor %.3f, %d levels\n", view.scales().scale_factor, view.scales().levels);
  if (const auto session = view.session_summary()) {
    std::printf("session       checkpoint of %s: %zu frames tracked, resumes at frame %llu (flatslam run --resume)%s\n",
                session->dataset.c_str(), view.session_frame_count(),
                static_cast<unsigned long long>(session->next_frame),
                session->global_adjustment_pending ? "; a global bundle adjustment after a loop pending" : "");
  }
  std::printf("maps          %zu\n", view.map_count());
  for (size_t m = 0; m < view.map_count(); ++m) {
    std::string agents;
    for (uint32_t a : view.agents(m)) {
      if (!agents.empty()) agents += ',';
      agents += std::to_string(a);
    }
    std::printf("map %-9u agents [%s], %zu keyframes, %zu map points, %zu observations, %zu keypoints\n",
                view.map_id(m), agents.c_str(), view.keyframe_count(m), view.point_count(m), view.observation_count(m),
                view.keypoint_count(m));
    const BoundingBox box = view.bounds(m);
    if (box.empty) {
      std::printf("              bounding box: empty\n");
    } else {
      std::printf("              bounding box [%.3f %.3f %.3f] .. [%.3f %.3f %.3f] m\n", box.min.x(), box.min.y(),
                  box.min.z(), box.max.x(), box.max.y(), box.max.z());
    }
  }
  return 0;
}

int Verify(const std::string& file, const Args& args) {
  SnapshotReadOptions options;
  if (auto c = args.get("vocabulary-checksum")) {
    try {
      options.vocabulary_checksum = std::stoull(*c, nullptr, 0);
    } catch (const std::exception&) {
      throw UsageError{"--vocabulary-checksum expects a number, got '" + *c + "'"};
    }
  }
  try {
    const LoadedSnapshot loaded = LoadMapSnapshot(file, options);
    size_t keyframes = 0, points = 0;
    for (const LoadedMap& m : loaded.maps) {
      keyframes += m.map.keyframes().size();
      points += m.map.points().size();
    }
    std::printf("ok: %s (format version %u, %zu maps, %zu keyframes, %zu map points)\n", file.c_str(),
                loaded.format_version, loaded.maps.size(), keyframes, points);
    // Stereo: the rig as each map measures it (mapping/rig_check.h); the offset its run took off
    // is not stored, so what it names is to be added to that one.
    if (loaded.metadata.calibration.sensor == Sensor::kStereo) {
      const CameraGeometry geometry =
          MergeCamera::FromCalibration(loaded.metadata.calibration, loaded.metadata.scales, 0).geometry;
      for (const LoadedMap& m : loaded.maps)
        if (const DisparityOffsetFit fit = FitDisparityOffset(m.map, geometry); fit.ok)
          std::printf("stereo rig    map %u: %s\n", m.id, DescribeDisparityOffset(fit, std::nan("")).c_str());
    }
    return 0;
  } catch (const Error& e) {
    std::printf("failed: %s\n", e.what());
    return 1;
  }
}

void WritePly(const std::string& path, const MapSnapshotView& view, bool binary) {
  size_t count = 0;
  for (size_t m = 0; m < view.map_count(); ++m) count += view.point_count(m);
  std::ofstream out(path, std::ios::binary);
  FLATSLAM_CHECK(out.good(), "cannot write ", path);
  out << "ply\nformat " << (binary ? "binary_little_endian" : "ascii") << " 1.0\n"
      << "comment flatslam map points (world frame, metres)\n"
      << "element vertex " << count << "\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
  char line[96];
  for (size_t m = 0; m < view.map_count(); ++m) {
    for (size_t i = 0; i < view.point_count(m); ++i) {
      const Eigen::Vector3f p = view.point_position(m, i).cast<float>();
      if (binary) {
        out.write(reinterpret_cast<const char*>(p.data()), 3 * sizeof(float));
      } else {
        const int n = std::snprintf(line, sizeof(line), "%.6g %.6g %.6g\n", p.x(), p.y(), p.z());
        out.write(line, n);
      }
    }
  }
  FLATSLAM_CHECK(out.good(), "cannot write ", path);
}

int Export(const std::string& file, const Args& args) {
  const auto ply = args.get("ply");
  const auto trajectory = args.get("trajectory");
  const auto colmap = args.get("colmap");
  if (!ply && !trajectory && !colmap)
    throw UsageError{"export needs --ply FILE, --trajectory FILE and/or --colmap DIR"};
  const std::string format = args.get_or("ply-format", "ascii");
  if (format != "ascii" && format != "binary") throw UsageError{"--ply-format is ascii or binary"};
  const std::string trajectory_format = args.get_or("format", "tum");
  if (trajectory_format != "tum" && trajectory_format != "kitti" && trajectory_format != "euroc")
    throw UsageError{"--format is tum, kitti or euroc"};
  if (args.has("format") && !trajectory) throw UsageError{"--format applies to --trajectory"};
  if (args.has("agent") && !trajectory) throw UsageError{"--agent applies to --trajectory"};
  const int64_t agent_arg = args.get_int("agent", 0);
  if (agent_arg < 0 || agent_arg > std::numeric_limits<uint32_t>::max())
    throw UsageError{"--agent must be an agent id (0 or more)"};
  const std::optional<uint32_t> agent =
      args.has("agent") ? std::optional(static_cast<uint32_t>(agent_arg)) : std::nullopt;
  const int64_t min_track_arg = args.get_int("min-track", 1);
  if (min_track_arg < 1) throw UsageError{"--min-track must be at least 1"};
  if (args.has("min-track") && !colmap) throw UsageError{"--min-track applies to --colmap"};
  const size_t min_track = static_cast<size_t>(min_track_arg);
  const MapSnapshotView view = MapSnapshotView::Open(file);
  // A COLMAP model needs the whole map (keypoints, observations), not only what the view reads in
  // place. Loaded before anything is written, so a map that does not rebuild leaves no output.
  const std::optional<LoadedSnapshot> loaded = colmap ? std::optional(LoadMapSnapshot(view)) : std::nullopt;
  if (ply) {
    WritePly(*ply, view, format == "binary");
    size_t count = 0;
    for (size_t m = 0; m < view.map_count(); ++m) count += view.point_count(m);
    std::printf("wrote %s: %zu map points (%s)\n", ply->c_str(), count, format.c_str());
  }
  if (trajectory) {
    Trajectory all;
    for (size_t m = 0; m < view.map_count(); ++m) {
      const Trajectory t = view.KeyFrameTrajectory(m, agent);
      all.insert(all.end(), t.begin(), t.end());
    }
    std::stable_sort(all.begin(), all.end(), [](const TimedPose& a, const TimedPose& b) { return a.t_ns < b.t_ns; });
    if (agent && all.empty()) {
      std::string present;
      for (size_t m = 0; m < view.map_count(); ++m)
        for (uint32_t a : view.agents(m)) {
          if (!present.empty()) present += ',';
          present += std::to_string(a);
        }
      FLATSLAM_CHECK(false, file, " has no keyframes of agent ", *agent, " (its maps hold agents [", present, "])");
    }
    if (trajectory_format == "kitti") {
      WriteKitti(*trajectory, all);
      WriteKittiTimes(*trajectory + ".times.txt", all);
    } else if (trajectory_format == "euroc") {
      WriteEuroc(*trajectory, all);
    } else {
      WriteTum(*trajectory, all);
    }
    std::printf("wrote %s: %zu keyframe poses (%s)\n", trajectory->c_str(), all.size(), trajectory_format.c_str());
  }
  if (colmap) {
    for (const ColmapMapExport& e : WriteColmapModels(*loaded, *colmap, min_track)) {
      const ColmapExportCounts& c = e.counts;
      std::printf("wrote %s: map %u, %zu images, %zu points, %zu observations, mean reprojection error %.3f px",
                  e.dir.c_str(), e.map_id, c.images, c.points, c.observations, c.mean_reprojection_error_px);
      if (c.points_left_out > 0)
        std::printf(" (%zu map points seen by fewer than %zu keyframes left out)", c.points_left_out,
                    std::max<size_t>(min_track, 1));
      std::printf("\n");
    }
  }
  return 0;
}

// How a session's camera came from the dataset's, for a merge's error: "the given camera" or the
// refinement a monocular run made from its own map (SnapshotMetadata::camera_refit).
std::string CameraOrigin(const SnapshotMetadata& m) {
  if (!m.camera_refit.refined()) return "the camera as given";
  char text[96];
  std::snprintf(text, sizeof text, "refined from its own map: k1 %+.4f, focal length %+.2f%%", m.camera_refit.k1,
                100 * (m.camera_refit.focal_scale - 1));
  return text;
}

// The camera a session was given before any refinement: its calibration's when it refined none,
// else the one its snapshot recorded (none in snapshots saved before they did).
std::optional<PinholeCamera> GivenCamera(const SnapshotMetadata& m) {
  if (!m.camera_refit.refined()) return m.calibration.camera;
  if (m.given_camera.fx <= 0) return std::nullopt;
  return m.given_camera;
}

// A session's keypoints into another session's camera: two refinements of one given camera.
struct CameraMove {
  RefinedCamera from, to;
  std::string from_origin, to_origin;  // CameraOrigin of each
};

// The move of monocular session m's keypoints into session into's camera, when both record the
// camera they were given and it is the same one.
std::optional<CameraMove> CameraMoveBetween(const SnapshotMetadata& m, const SnapshotMetadata& into) {
  if (m.calibration.sensor != Sensor::kMonocular || into.calibration.sensor != Sensor::kMonocular)
    return std::nullopt;
  const std::optional<PinholeCamera> given = GivenCamera(m), given_into = GivenCamera(into);
  if (!given || !given_into) return std::nullopt;
  Calibration a = m.calibration, b = into.calibration;
  a.camera = *given;
  b.camera = *given_into;
  if (!SameCamera(a, b)) return std::nullopt;
  return CameraMove{RefinedCamera(*given, m.camera_refit), RefinedCamera(*given_into, into.camera_refit),
                    CameraOrigin(m), CameraOrigin(into)};
}

// Why two sessions whose runs refined the camera differently cannot merge, and what to do, for
// the calibration error ("" when the refinements agree: the cameras simply differ).
std::string RefitHint(const std::string& in, const SnapshotMetadata& m, const std::string& first_in,
                      const SnapshotMetadata& first) {
  if (first.camera_refit == m.camera_refit) return "";
  const std::string used = "; " + in + "'s session used " + CameraOrigin(m) + ", " + first_in + "'s " +
                           CameraOrigin(first);
  if (GivenCamera(first) && GivenCamera(m)) return used + ", of another given camera";
  return used + ", and a snapshot saved before snapshots recorded the camera a session was given cannot be "
                "re-expressed in another: run the later sessions with --camera-from " +
         first_in + " (or all with --keep-camera)";
}

int Merge(const std::vector<std::string>& inputs, const Args& args) {
  const auto out = args.get("out");
  if (!out) throw UsageError{"merge needs -o OUT"};
  if (inputs.size() < 2) throw UsageError{"merge needs at least two input snapshots"};
  const std::filesystem::path out_path(*out);
  for (const std::string& in : inputs) {
    std::error_code ec;
    const bool same = std::filesystem::exists(out_path, ec) && std::filesystem::equivalent(out_path, in, ec);
    if (same || std::filesystem::weakly_canonical(out_path, ec) == std::filesystem::weakly_canonical(in, ec))
      throw UsageError{"-o " + *out + " is an input; inputs are never modified"};
  }
  const std::filesystem::path dir = out_path.has_parent_path() ? out_path.parent_path() : ".";
  FLATSLAM_CHECK(std::filesystem::is_directory(dir), "-o ", *out, ": directory ", dir, " does not exist");
  MapMergeOptions options;
  options.min_matches = static_cast<int>(args.get_int("min-matches", options.min_matches));
  options.min_consistent_pairs = static_cast<int>(args.get_int("min-pairs", options.min_consistent_pairs));
  options.refine = args.has("refine");
  options.close_loops = args.has("close-loops");
  options.bundle_adjustment.num_threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  options.seed = static_cast<uint64_t>(args.get_int("seed", static_cast<int64_t>(options.seed)));
  if (!options.Check()) throw UsageError{"--min-matches and --min-pairs must be at least 3 and 1"};

  const auto start = std::chrono::steady_clock::now();
  // Load everything first: any bad input stops the command before work is done or anything written.
  // The inputs and the vocabulary load side by side; failures and mismatches are then reported
  // input by input in command-line order (the vocabulary last), as a load one by one would.
  const std::filesystem::path vocabulary_path =
      args.get("vocabulary") ? std::filesystem::path(*args.get("vocabulary")) : DefaultVocabularyPath();
  std::vector<std::optional<LoadedSnapshot>> loaded(inputs.size());
  std::vector<std::exception_ptr> failed(inputs.size() + 1);
  Vocabulary vocabulary;
  tbb::parallel_for(size_t{0}, inputs.size() + 1, [&](size_t i) {
    try {
      if (i < inputs.size())
        loaded[i] = LoadMapSnapshot(inputs[i]);
      else
        vocabulary = Vocabulary::Load(vocabulary_path);
    } catch (...) {
      failed[i] = std::current_exception();
    }
  });
  std::vector<LoadedSnapshot> snapshots;
  std::vector<std::optional<CameraMove>> moves;  // per input: into the first input's camera
  for (size_t i = 0; i < inputs.size(); ++i) {
    const std::string& in = inputs[i];
    if (failed[i]) std::rethrow_exception(failed[i]);
    snapshots.push_back(std::move(*loaded[i]));
    loaded[i].reset();
    const SnapshotMetadata& first = snapshots.front().metadata;
    const SnapshotMetadata& m = snapshots.back().metadata;
    // Sessions of one camera whose runs refined it differently saw their images through different
    // models: their keypoints are re-expressed in the first one's camera through the camera both
    // were given (snapshots that do not record it are refused).
    std::optional<CameraMove> move;
    if (!SameCamera(first.calibration, m.calibration)) move = CameraMoveBetween(m, first);
    FLATSLAM_CHECK(move || SameCamera(first.calibration, m.calibration), "cannot merge ", in,
                   ": its calibration (",
                   SensorName(m.calibration.sensor), ", ", m.calibration.camera.width, "x", m.calibration.camera.height,
                   ", fx ", m.calibration.camera.fx, ") differs from ", inputs.front(), " (",
                   SensorName(first.calibration.sensor), ", ", first.calibration.camera.width, "x",
                   first.calibration.camera.height, ", fx ", first.calibration.camera.fx, ")",
                   RefitHint(in, m, inputs.front(), first));
    moves.push_back(std::move(move));
    FLATSLAM_CHECK(first.scales.scale_factor == m.scales.scale_factor && first.scales.levels == m.scales.levels,
                   "cannot merge ", in, ": its scale pyramid differs from ", inputs.front());
    auto vocabulary_name = [](uint64_t checksum) {
      char text[40];
      std::snprintf(text, sizeof(text), "vocabulary %016llx", static_cast<unsigned long long>(checksum));
      return checksum == 0 ? std::string("no vocabulary") : std::string(text);
    };
    FLATSLAM_CHECK(VirtualBaseline(first) == VirtualBaseline(m) || first.calibration.sensor != Sensor::kRgbd,
                   "cannot merge ", in, ": its RGB-D virtual baseline (", VirtualBaseline(m), " m) differs from ",
                   inputs.front(), " (", VirtualBaseline(first), " m)");
    FLATSLAM_CHECK(first.vocabulary_checksum == m.vocabulary_checksum, "cannot merge ", in, ": built with ",
                   vocabulary_name(m.vocabulary_checksum), ", ", inputs.front(), " with ",
                   vocabulary_name(first.vocabulary_checksum));
  }
  const SnapshotMetadata metadata = snapshots.front().metadata;
  if (failed.back()) std::rethrow_exception(failed.back());
  if (metadata.vocabulary_checksum != 0) {
    FLATSLAM_CHECK(vocabulary.checksum() == metadata.vocabulary_checksum, "vocabulary ", vocabulary_path.string(),
                   " (checksum ", std::hex, vocabulary.checksum(), ") is not the one the maps were built with (",
                   metadata.vocabulary_checksum, "); pass it with --vocabulary");
  } else {
    std::printf("note          the maps record no vocabulary; place recognition uses %s\n", vocabulary_path.c_str());
  }
  std::vector<Map> maps;
  std::vector<std::string> names;
  const MergeCamera camera = MergeCamera::FromCalibration(metadata.calibration, metadata.scales, 0);
  for (size_t f = 0; f < snapshots.size(); ++f) {
    for (LoadedMap& m : snapshots[f].maps) {
      names.push_back(inputs[f] + "#" + std::to_string(m.id));
      if (const std::optional<CameraMove>& move = moves[f]) {
        const CameraChange c = ReexpressMapCamera(m.map, move->from, move->to, camera, options);
        std::printf("camera        %s: keypoints from %s into %s's %s: %zu moved, up to %.2f px, %zu observations "
                    "left the image; adjusted alone, %zu outliers (%.0f ms)\n",
                    names.back().c_str(), move->from_origin.c_str(), inputs.front().c_str(), move->to_origin.c_str(),
                    c.keypoints, c.max_shift_px, c.observations_erased, c.adjustment.outliers, c.adjustment.ms);
      }
      maps.push_back(std::move(m.map));
    }
  }
  snapshots.clear();
  for (size_t i = 0; i < maps.size(); ++i)
    std::printf("input %-7zu %s: agents [%s], %zu keyframes, %zu map points\n", i, names[i].c_str(),
                Agents(maps[i]).c_str(), maps[i].keyframes().size(), maps[i].points().size());
  const double load_ms = MsSince(start);

  const MergeTimes times = MergeAndSave(std::move(maps), vocabulary, metadata, options, out_path);
  std::printf("time          load %.0f ms, merge %.0f ms, save %.0f ms\n", load_ms, times.merge_ms, times.save_ms);
  return 0;
}

int Calibrate(const std::string& file, const Args& args) {
  const auto settings_out = args.get("settings-out");
  const auto out = args.get("out");
  LoadedSnapshot loaded = LoadMapSnapshot(file);
  const Calibration& calibration = loaded.metadata.calibration;
  if (settings_out && calibration.sensor != Sensor::kMonocular)
    throw UsageError{"--settings-out writes a monocular camera; " + file + " holds a " +
                     SensorName(calibration.sensor) + " map (a stereo pair with distortion needs its rectification)"};
  if (out && calibration.sensor != Sensor::kMonocular)
    throw UsageError{"-o refines a monocular camera; " + file + " holds a " + SensorName(calibration.sensor) + " map"};
  if ((settings_out || out) && loaded.maps.size() != 1)
    throw UsageError{std::string(out ? "-o" : "--settings-out") + " needs a snapshot of one map; " + file + " holds " +
                     std::to_string(loaded.maps.size())};
  const CameraGeometry geometry = MergeCamera::FromCalibration(calibration, loaded.metadata.scales, 0).geometry;
  const PinholeCamera& camera = calibration.camera;
  std::optional<CameraCheck> written;
  for (const LoadedMap& m : loaded.maps) {
    const auto start = std::chrono::steady_clock::now();
    const CameraCheck check = CheckCameraModel(m.map, geometry);
    if (!check.ok) {
      if (check.observations < kCameraCheckMinObservations)
        std::printf("camera        map %u: too few observations to tell (%zu of points whose rays fix them, of at "
                    "least %zu)\n",
                    m.id, check.observations, kCameraCheckMinObservations);
      else
        std::printf("camera        map %u: no solution (the adjustment or its standard errors failed)\n", m.id);
      continue;
    }
    std::printf("camera        map %u (%.1f s): %s\n", m.id, MsSince(start) / 1000.0,
                DescribeCameraCheck(check, camera).c_str());
    written = check;
  }
  if (out && written) {
    // The map re-expressed in the camera it asks for: every keypoint moved from the model the
    // session saw its images through to the refined one (through the given camera), then the
    // map adjusted alone in it to convergence (ReexpressMapCamera), so keyframes and points
    // shed what they had bent to fit the old model.
    const SnapshotMetadata& m = loaded.metadata;
    const std::optional<PinholeCamera> given = GivenCamera(m);
    if (!given)
      Fail(file, " was saved before snapshots recorded the camera a session was given: its refined camera cannot "
           "be refined again (rerun the session with --settings from --settings-out)");
    LoadedMap& map = loaded.maps.front();
    const MapCameraRefinement r = RefineMapCamera(map.map, m.calibration, m.scales, *given, m.camera_refit,
                                                  CameraRefit{written->focal_scale, written->k1});
    SnapshotMetadata metadata = m;
    metadata.calibration = r.calibration;
    metadata.camera_refit = r.refit;
    metadata.given_camera = *given;
    const CameraChange& c = r.change;
    std::printf("camera        keypoints into the refined camera (fx %.2f, k1 %+.4f over the given): %zu moved, up "
                "to %.2f px, %zu observations left the image; adjusted, %zu outliers (%.0f ms)\n",
                r.calibration.camera.fx, r.refit.k1, c.keypoints, c.max_shift_px, c.observations_erased,
                c.adjustment.outliers, c.adjustment.ms);
    const SnapshotMapRef ref{map.id, &map.map};
    SaveMapSnapshot(*out, std::span<const SnapshotMapRef>(&ref, 1), metadata);
    std::printf("wrote         %s\n", out->c_str());
  }
  if (!settings_out) return 0;
  if (!written) {
    std::fprintf(stderr, "flatslam map: %s: no refined camera to write to %s\n", file.c_str(), settings_out->c_str());
    return 1;
  }
  WriteFileAtomically(*settings_out, [&](std::FILE* out) {
    std::fprintf(out,
                 "%%YAML:1.0\n"
                 "# refined by `flatslam map calibrate %s`: focal length and a radial term fitted to the map;\n"
                 "# k1 applies to the images as the map saw them (undistorted): for a dataset with a\n"
                 "# distortion of its own it is a residual on top of that one, not a replacement\n"
                 "Camera.fx: %.6f\nCamera.fy: %.6f\nCamera.cx: %.6f\nCamera.cy: %.6f\n"
                 "Camera.k1: %.6f\nCamera.k2: 0.0\nCamera.p1: 0.0\nCamera.p2: 0.0\n",
                 file.c_str(), camera.fx * written->focal_scale, camera.fy * written->focal_scale, camera.cx, camera.cy,
                 written->k1);
    if (calibration.frame_rate_hz > 0) std::fprintf(out, "Camera.fps: %.6f\n", calibration.frame_rate_hz);
  });
  std::printf("wrote         %s\n", settings_out->c_str());
  return 0;
}

}  // namespace

int RunMap(const std::vector<std::string>& argv) {
  std::vector<std::string> expanded = argv;  // -o is short for --out
  for (std::string& a : expanded)
    if (a == "-o") a = "--out";
  const Args args(expanded,
                  {"ply", "ply-format", "trajectory", "format", "agent", "colmap", "min-track", "vocabulary-checksum",
                   "out", "vocabulary", "min-matches", "min-pairs", "seed", "settings-out"},
                  {"refine", "close-loops"});
  if (args.help()) {
    std::fputs(kMapUsage, stdout);
    return 0;
  }
  const auto& pos = args.positional();
  if (pos.empty()) throw UsageError{"expected a subcommand: info, verify, export, calibrate or merge"};
  if (pos[0] == "merge") return Merge(std::vector<std::string>(pos.begin() + 1, pos.end()), args);
  if (pos.size() != 2) throw UsageError{"expected: map " + pos[0] + " FILE"};
  if (pos[0] == "info") return Info(pos[1]);
  if (pos[0] == "verify") return Verify(pos[1], args);
  if (pos[0] == "export") return Export(pos[1], args);
  if (pos[0] == "calibrate") return Calibrate(pos[1], args);
  throw UsageError{"unknown map subcommand '" + pos[0] + "' (info, verify, export, calibrate, merge)"};
}

}  // namespace flatslam::app
