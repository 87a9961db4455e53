// flatslam map: describe, verify and export map snapshots (files written by `run --save-map`).
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <string>

#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "storage/snapshot.h"
#include "trajectory/trajectory_io.h"

namespace flatslam::app {

const char* const kMapUsage =
    "usage: flatslam map info FILE\n"
    "       flatslam map verify FILE [--vocabulary-checksum N]\n"
    "       flatslam map export FILE [--ply points.ply] [--ply-format ascii|binary] [--trajectory traj.tum]\n\n"
    "Map snapshots (.fsmap) hold one or more maps with their keyframes, map points and graph edges.\n"
    "  info     format version, file size, vocabulary checksum, calibration, and per map: id,\n"
    "           agents, keyframes, map points, observations, bounding box (read in place: fast)\n"
    "  verify   checks everything: structure, every index, the content hash, that each map\n"
    "           rebuilds consistently; prints 'ok' and exits 0, else the problem and exits 1\n"
    "  export   map points as a PLY point cloud (all maps; ascii by default) and the keyframe\n"
    "           trajectory (T_world_cam, TUM format, sorted by time; with several maps the\n"
    "           poses of each stay in that map's own frame)\n";

namespace {

int Info(const std::string& file) {
  SnapshotReadOptions options;
  options.verify_content_hash = false;  // structure and indices only: milliseconds on any size
  const auto start = std::chrono::steady_clock::now();
  const MapSnapshotView view = MapSnapshotView::Open(file, options);
  const double open_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
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
  if (calib.frame_rate_hz > 0) std::printf(", %.1f Hz", calib.frame_rate_hz);
  std::printf("\nscales        factor %.3f, %d levels\n", view.scales().scale_factor, view.scales().levels);
  std::printf("maps          %zu\n", view.map_count());
  for (size_t m = 0; m < view.map_count(); ++m) {
    std::string agents;
    for (uint32_t a : view.agents(m)) agents += (agents.empty() ? "" : ",") + std::to_string(a);
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
  if (!ply && !trajectory) throw UsageError{"export needs --ply FILE and/or --trajectory FILE"};
  const std::string format = args.get_or("ply-format", "ascii");
  if (format != "ascii" && format != "binary") throw UsageError{"--ply-format is ascii or binary"};
  const MapSnapshotView view = MapSnapshotView::Open(file);
  if (ply) {
    WritePly(*ply, view, format == "binary");
    size_t count = 0;
    for (size_t m = 0; m < view.map_count(); ++m) count += view.point_count(m);
    std::printf("wrote %s: %zu map points (%s)\n", ply->c_str(), count, format.c_str());
  }
  if (trajectory) {
    Trajectory all;
    for (size_t m = 0; m < view.map_count(); ++m) {
      const Trajectory t = view.KeyFrameTrajectory(m);
      all.insert(all.end(), t.begin(), t.end());
    }
    std::stable_sort(all.begin(), all.end(), [](const TimedPose& a, const TimedPose& b) { return a.t_ns < b.t_ns; });
    WriteTum(*trajectory, all);
    std::printf("wrote %s: %zu keyframe poses\n", trajectory->c_str(), all.size());
  }
  return 0;
}

}  // namespace

int RunMap(const std::vector<std::string>& argv) {
  const Args args(argv, {"ply", "ply-format", "trajectory", "vocabulary-checksum"}, {});
  if (args.help()) {
    std::fputs(kMapUsage, stdout);
    return 0;
  }
  const auto& pos = args.positional();
  if (pos.empty()) throw UsageError{"expected a subcommand: info, verify or export"};
  if (pos.size() != 2) throw UsageError{"expected: map " + pos[0] + " FILE"};
  if (pos[0] == "info") return Info(pos[1]);
  if (pos[0] == "verify") return Verify(pos[1], args);
  if (pos[0] == "export") return Export(pos[1], args);
  throw UsageError{"unknown map subcommand '" + pos[0] + "' (info, verify, export)"};
}

}  // namespace flatslam::app
