#include "storage/colmap_export.h"

#include <algorithm>
#include <cstdio>
#include <string>
#include <system_error>
#include <unordered_set>

#include <Eigen/Geometry>

#include "core/atomic_write.h"
#include "core/error.h"
#include "trajectory/trajectory_io.h"

namespace flatslam {
namespace {

// COLMAP's pixel grid puts the centre of the first pixel at (0.5, 0.5), flatslam's at (0, 0).
constexpr double kPixelShift = 0.5;

void CreateDirectory(const std::filesystem::path& dir) {
  std::error_code ec;
  std::filesystem::create_directories(dir, ec);
  const bool is_dir = std::filesystem::is_directory(dir);
  FLATSLAM_CHECK(!ec && is_dir, dir.string(), ": cannot create the directory (",
                 ec ? ec.message() : std::string("exists and is not a directory"), ")");
}

// Image names: stable (derived from the keyframe, not from the export) and unique within the model.
std::vector<std::string> ImageNames(const Map& map) {
  const auto keyframes = map.keyframes().values();
  std::vector<uint32_t> agents;
  for (const KeyFrame& kf : keyframes) agents.push_back(kf.agent);
  std::sort(agents.begin(), agents.end());
  const bool several_agents = !agents.empty() && agents.front() != agents.back();
  std::vector<std::string> names;
  names.reserve(keyframes.size());
  std::unordered_set<std::string> taken;
  for (const KeyFrame& kf : keyframes) {
    // Agents of a merged map record their own clocks, which may well give equal times.
    const std::string stem =
        (several_agents ? "agent" + std::to_string(kf.agent) + "/" : std::string()) + std::to_string(kf.t_ns);
    std::string name = stem + ".png";
    if (!taken.insert(name).second) {
      name = stem + "-kf" + std::to_string(kf.id) + ".png";
      FLATSLAM_CHECK(taken.insert(name).second, "two keyframes with id ", kf.id, " and time ", kf.t_ns, " in one map");
    }
    names.push_back(std::move(name));
  }
  return names;
}

// Mean pixel distance between the point's projections and the keypoints that observe it, over the
// observations in front of their camera (0 when none is).
double MeanReprojectionError(const Map& map, const MapPoint& point, const PinholeCamera& camera) {
  double sum = 0;
  size_t count = 0;
  for (const Observation& o : point.observations) {
    const KeyFrame& kf = map.keyframe(o.keyframe);
    const Eigen::Vector3d x = kf.T_cam_world * point.position;
    if (!(x.z() > 0)) continue;
    sum += (camera.Project(x) - kf.uv[o.keypoint].cast<double>()).norm();
    ++count;
  }
  return count == 0 ? 0.0 : sum / static_cast<double>(count);
}

// The sensor's name for a comment (SensorName lives in the io library, which storage does not link).
const char* SensorLabel(Sensor sensor) {
  switch (sensor) {
    case Sensor::kMonocular:
      return "monocular";
    case Sensor::kStereo:
      return "stereo";
    case Sensor::kRgbd:
      return "RGB-D";
  }
  return "unknown";
}

}  // namespace

ColmapExportCounts WriteColmapModel(const Map& map, const Calibration& calibration, const std::filesystem::path& dir,
                                    size_t min_track) {
  const PinholeCamera& camera = calibration.camera;
  FLATSLAM_CHECK(camera.valid(), dir.string(), ": cannot export a COLMAP model without a valid camera (", camera.width,
                 "x", camera.height, ", fx ", camera.fx, ", fy ", camera.fy, ")");
  CreateDirectory(dir);
  constexpr int kCameraId = 1;
  const auto keyframes = map.keyframes().values();
  const auto points = map.points().values();

  const size_t shortest = std::max<size_t>(min_track, 1);
  auto exported = [&](const MapPoint& p) { return p.observations.size() >= shortest; };
  ColmapExportCounts counts;
  counts.images = keyframes.size();
  size_t all_observations = 0;
  for (const MapPoint& p : points) {
    all_observations += p.observations.size();
    if (!exported(p)) {
      ++counts.points_left_out;
    } else {
      ++counts.points;
      counts.observations += p.observations.size();
    }
  }
  // Tracks come from the points, POINTS2D from the keyframes: the Map invariant (Map::Validate)
  // makes them the same links. Checked before writing, so a broken map leaves no model behind.
  size_t bound = 0;
  for (const KeyFrame& kf : keyframes)
    for (PointHandle p : kf.points) bound += map.points().contains(p) ? 1 : 0;
  FLATSLAM_CHECK(bound == all_observations, dir.string(), ": the map is inconsistent (", bound,
                 " keypoints bound to points, ", all_observations, " point observations)");
  const std::vector<std::string> names = ImageNames(map);  // may refuse the map: before any file

  WriteFileAtomically(dir / "cameras.txt", [&](std::FILE* out) {
    std::fprintf(out,
                 "# flatslam map as a COLMAP camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                 "# %s sensor, images undistorted and rectified: the left (colour) camera only\n"
                 "# Number of cameras: 1\n",
                 SensorLabel(calibration.sensor));
    std::fprintf(out, "%d PINHOLE %d %d %.17g %.17g %.17g %.17g\n", kCameraId, camera.width, camera.height, camera.fx,
                 camera.fy, camera.cx + kPixelShift, camera.cy + kPixelShift);
  });

  WriteFileAtomically(dir / "images.txt", [&](std::FILE* out) {
    std::fprintf(out,
                 "# flatslam keyframes as a COLMAP image list, two lines per image:\n"
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME (world-to-camera; names are labels)\n"
                 "#   POINTS2D[] as (X, Y, POINT3D_ID), the keyframe's keypoints in order\n"
                 "# Number of images: %zu, mean observations per image: %.6g\n",
                 counts.images, counts.images == 0 ? 0.0 : static_cast<double>(counts.observations) / counts.images);
    for (size_t i = 0; i < keyframes.size(); ++i) {
      const KeyFrame& kf = keyframes[i];
      const Eigen::Quaterniond q = CanonicalQuaternion(kf.T_cam_world.linear());
      const Eigen::Vector3d& t = kf.T_cam_world.translation();
      std::fprintf(out, "%zu %.17g %.17g %.17g %.17g %.17g %.17g %.17g %d %s\n", i + 1, q.w(), q.x(), q.y(), q.z(),
                   t.x(), t.y(), t.z(), kCameraId, names[i].c_str());
      for (size_t k = 0; k < kf.size(); ++k) {
        const double u = kf.uv[k].x() + kPixelShift, v = kf.uv[k].y() + kPixelShift;
        const PointHandle p = kf.points[k];
        const MapPoint* point = p.is_null() ? nullptr : map.points().try_get(p);
        // A keypoint bound to a point is one of that point's observations (Map invariant); the
        // point is exported under this id unless its track is too short.
        const long long id =
            point != nullptr && exported(*point) ? static_cast<long long>(map.points().dense_index(p)) + 1 : -1;
        std::fprintf(out, "%s%.9g %.9g %lld", k == 0 ? "" : " ", u, v, id);
      }
      std::fputc('\n', out);
    }
  });

  double error_sum = 0;
  WriteFileAtomically(dir / "points3D.txt", [&](std::FILE* out) {
    std::fprintf(out,
                 "# flatslam map points as a COLMAP 3D point list, one line per point:\n"
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                 "# Number of points: %zu, mean track length: %.6g\n",
                 counts.points, counts.points == 0 ? 0.0 : static_cast<double>(counts.observations) / counts.points);
    for (size_t i = 0; i < points.size(); ++i) {
      const MapPoint& point = points[i];
      if (!exported(point)) continue;
      const double error = MeanReprojectionError(map, point, camera);
      error_sum += error;
      std::fprintf(out, "%zu %.17g %.17g %.17g 128 128 128 %.6g", i + 1, point.position.x(), point.position.y(),
                   point.position.z(), error);
      for (const Observation& o : point.observations)
        std::fprintf(out, " %zu %u", map.keyframes().dense_index(o.keyframe) + 1, o.keypoint);
      std::fputc('\n', out);
    }
  });
  counts.mean_reprojection_error_px = counts.points == 0 ? 0.0 : error_sum / static_cast<double>(counts.points);
  return counts;
}

std::vector<ColmapMapExport> WriteColmapModels(const LoadedSnapshot& snapshot, const std::filesystem::path& dir,
                                               size_t min_track) {
  FLATSLAM_CHECK(!snapshot.maps.empty(), dir.string(), ": the snapshot holds no map to export");
  std::vector<ColmapMapExport> exports;
  for (const LoadedMap& m : snapshot.maps) {
    ColmapMapExport e;
    e.map_id = m.id;
    e.dir = snapshot.maps.size() == 1 ? dir : dir / std::to_string(m.id);
    e.counts = WriteColmapModel(m.map, snapshot.metadata.calibration, e.dir, min_track);
    exports.push_back(std::move(e));
  }
  return exports;
}

}  // namespace flatslam
