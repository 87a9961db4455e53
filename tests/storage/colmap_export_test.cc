// COLMAP text models from maps: the three files parsed back (counts, tracks that agree with the
// images' POINTS2D, world-to-camera poses, pixel shift, reprojection error), one folder per map
// for snapshots of several maps, errors naming the path, and COLMAP's own model_analyzer reading
// the model with the same numbers of images, points and observations (skipped without COLMAP).
#include "storage/colmap_export.h"

#include <array>
#include <cstdlib>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/error.h"
#include "storage/random_map.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

constexpr const char* kColmap = "/usr/bin/colmap";

struct ColmapCamera {
  int id = 0;
  std::string model;
  int width = 0, height = 0;
  std::vector<double> params;
};

struct ColmapPoint2D {
  double x = 0, y = 0;
  long long point_id = -1;
};

struct ColmapImage {
  long long id = 0;
  Eigen::Quaterniond q;
  Eigen::Vector3d t;
  int camera_id = 0;
  std::string name;
  std::vector<ColmapPoint2D> points2d;
};

struct ColmapPoint3D {
  long long id = 0;
  Eigen::Vector3d xyz;
  int rgb[3] = {0, 0, 0};
  double error = 0;
  std::vector<std::pair<long long, size_t>> track;  // (IMAGE_ID, POINT2D_IDX)
};

struct ColmapModel {
  std::vector<ColmapCamera> cameras;
  std::map<long long, ColmapImage> images;
  std::map<long long, ColmapPoint3D> points;
};

// Data lines of a COLMAP text file: comments dropped, but empty lines kept (an image without
// keypoints has an empty POINTS2D line).
std::vector<std::string> DataLines(const fs::path& path) {
  std::ifstream in(path);
  EXPECT_TRUE(in.good()) << path;
  std::vector<std::string> lines;
  std::string line;
  while (std::getline(in, line))
    if (line.empty() || line[0] != '#') lines.push_back(line);
  return lines;
}

ColmapModel ReadModel(const fs::path& dir) {
  ColmapModel model;
  for (const std::string& line : DataLines(dir / "cameras.txt")) {
    if (line.empty()) continue;
    std::istringstream in(line);
    ColmapCamera c;
    in >> c.id >> c.model >> c.width >> c.height;
    for (double v; in >> v;) c.params.push_back(v);
    model.cameras.push_back(c);
  }
  const std::vector<std::string> image_lines = DataLines(dir / "images.txt");
  EXPECT_EQ(image_lines.size() % 2, 0u) << "images.txt has two lines per image";
  for (size_t i = 0; i + 1 < image_lines.size(); i += 2) {
    std::istringstream in(image_lines[i]);
    ColmapImage image;
    double qw, qx, qy, qz;
    in >> image.id >> qw >> qx >> qy >> qz >> image.t.x() >> image.t.y() >> image.t.z() >> image.camera_id >>
        image.name;
    image.q = Eigen::Quaterniond(qw, qx, qy, qz);
    std::istringstream points(image_lines[i + 1]);
    for (ColmapPoint2D p; points >> p.x >> p.y >> p.point_id;) image.points2d.push_back(p);
    EXPECT_TRUE(model.images.emplace(image.id, image).second) << "image id " << image.id << " twice";
  }
  for (const std::string& line : DataLines(dir / "points3D.txt")) {
    if (line.empty()) continue;
    std::istringstream in(line);
    ColmapPoint3D p;
    in >> p.id >> p.xyz.x() >> p.xyz.y() >> p.xyz.z() >> p.rgb[0] >> p.rgb[1] >> p.rgb[2] >> p.error;
    for (std::pair<long long, size_t> e; in >> e.first >> e.second;) p.track.push_back(e);
    EXPECT_TRUE(model.points.emplace(p.id, p).second) << "point id " << p.id << " twice";
  }
  return model;
}

Calibration TestCalibration() {
  Calibration c;
  c.sensor = Sensor::kStereo;
  c.camera = {718.856, 718.5, 607.1928, 185.2157, 1241, 376};
  c.baseline_m = 0.537;
  return c;
}

// The numbers COLMAP prints for a model; nullopt-like -1 where a line is missing.
struct AnalyzerCounts {
  long long images = -1, registered = -1, points = -1, observations = -1;
  std::string output;
};

AnalyzerCounts RunModelAnalyzer(const fs::path& dir) {
  AnalyzerCounts counts;
  const std::string command = std::string(kColmap) + " model_analyzer --path '" + dir.string() + "' 2>&1";
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) return counts;
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) counts.output.append(buffer.data(), n);
  pclose(pipe);
  // Lines look like "I1124 12:00:00.000 model.cc:123] Registered images: 18" (glog) or bare.
  auto value = [&](const std::string& key) {
    const std::string tag = "] " + key + ": ";
    size_t at = counts.output.find(tag);
    size_t skip = tag.size();
    if (at == std::string::npos && counts.output.rfind(key + ": ", 0) == 0) at = 0, skip = key.size() + 2;
    if (at == std::string::npos) {
      at = counts.output.find("\n" + key + ": ");
      skip = key.size() + 3;
    }
    return at == std::string::npos ? -1LL : std::stoll(counts.output.substr(at + skip));
  };
  counts.images = value("Images");
  counts.registered = value("Registered images");
  counts.points = value("Points");
  counts.observations = value("Observations");
  return counts;
}

// Checks the model in dir against map: counts, tracks against POINTS2D, poses, keypoints, positions.
void ExpectModelMatchesMap(const fs::path& dir, const Map& map, const Calibration& calibration,
                           const ColmapExportCounts& counts) {
  const ColmapModel model = ReadModel(dir);
  ASSERT_EQ(model.cameras.size(), 1u);
  const ColmapCamera& camera = model.cameras[0];
  EXPECT_EQ(camera.model, "PINHOLE");
  EXPECT_EQ(camera.width, calibration.camera.width);
  EXPECT_EQ(camera.height, calibration.camera.height);
  ASSERT_EQ(camera.params.size(), 4u);
  EXPECT_DOUBLE_EQ(camera.params[0], calibration.camera.fx);
  EXPECT_DOUBLE_EQ(camera.params[1], calibration.camera.fy);
  EXPECT_DOUBLE_EQ(camera.params[2], calibration.camera.cx + 0.5);
  EXPECT_DOUBLE_EQ(camera.params[3], calibration.camera.cy + 0.5);

  size_t with_observations = 0, observations = 0;
  for (const MapPoint& p : map.points().values()) {
    with_observations += p.observations.empty() ? 0 : 1;
    observations += p.observations.size();
  }
  EXPECT_EQ(counts.images, map.keyframes().size());
  EXPECT_EQ(counts.points, with_observations);
  EXPECT_EQ(counts.observations, observations);
  EXPECT_EQ(counts.points_left_out, map.points().size() - with_observations);
  ASSERT_EQ(model.images.size(), map.keyframes().size());
  ASSERT_EQ(model.points.size(), with_observations);

  // Images: poses world-to-camera, keypoints in order (shifted by half a pixel), point ids.
  std::set<std::string> names;
  size_t bound = 0;
  const auto keyframes = map.keyframes().values();
  for (size_t i = 0; i < keyframes.size(); ++i) {
    const KeyFrame& kf = keyframes[i];
    const auto found = model.images.find(static_cast<long long>(i) + 1);
    ASSERT_NE(found, model.images.end()) << "no image for keyframe " << i;
    const ColmapImage& image = found->second;
    EXPECT_EQ(image.camera_id, camera.id);
    EXPECT_TRUE(names.insert(image.name).second) << "name " << image.name << " twice";
    EXPECT_NEAR(image.q.norm(), 1.0, 1e-12);
    // The image pose maps world points into the camera: it is T_cam_world, not its inverse.
    EXPECT_TRUE(image.q.toRotationMatrix().isApprox(kf.T_cam_world.linear(), 1e-12)) << image.name;
    EXPECT_TRUE(image.t.isApprox(kf.T_cam_world.translation(), 1e-12)) << image.name;
    ASSERT_EQ(image.points2d.size(), kf.size()) << image.name;
    for (size_t k = 0; k < kf.size(); ++k) {
      const ColmapPoint2D& p = image.points2d[k];
      EXPECT_NEAR(p.x, kf.uv[k].x() + 0.5, 1e-4);
      EXPECT_NEAR(p.y, kf.uv[k].y() + 0.5, 1e-4);
      if (kf.points[k].is_null()) {
        EXPECT_EQ(p.point_id, -1);
      } else {
        ++bound;
        EXPECT_EQ(p.point_id, static_cast<long long>(map.points().dense_index(kf.points[k])) + 1);
        EXPECT_TRUE(model.points.count(p.point_id)) << "image " << image.id << " names missing point " << p.point_id;
      }
    }
  }
  EXPECT_EQ(bound, observations);

  // Points: positions, grey, and every track entry names an image whose POINT2D there is this point.
  size_t track_entries = 0;
  const auto points = map.points().values();
  for (const auto& [id, point] : model.points) {
    ASSERT_GE(id, 1);
    ASSERT_LE(static_cast<size_t>(id), points.size());
    const MapPoint& mp = points[static_cast<size_t>(id - 1)];
    EXPECT_TRUE(point.xyz.isApprox(mp.position, 1e-14));
    EXPECT_EQ(point.rgb[0], 128);
    EXPECT_EQ(point.rgb[2], 128);
    EXPECT_GE(point.error, 0.0);
    EXPECT_EQ(point.track.size(), mp.observations.size());
    std::set<long long> images_seen;
    for (const auto& [image_id, idx] : point.track) {
      ++track_entries;
      EXPECT_TRUE(images_seen.insert(image_id).second) << "point " << id << " seen twice by image " << image_id;
      const auto image = model.images.find(image_id);
      ASSERT_NE(image, model.images.end()) << "point " << id << " track names missing image " << image_id;
      ASSERT_LT(idx, image->second.points2d.size());
      EXPECT_EQ(image->second.points2d[idx].point_id, id) << "image " << image_id << " keypoint " << idx;
    }
  }
  EXPECT_EQ(track_entries, observations);
}

void ExpectColmapAgrees(const fs::path& dir, const ColmapExportCounts& counts) {
  // The text model as exported, and as COLMAP's model_converter rewrites it in its binary format.
  // In a temp dir of its own (removed at exit), never beside `dir`, which may be a temp dir itself.
  const fs::path binary = testing::FreshTempDir("colmap_bin_" + dir.filename().string());
  const std::string convert = std::string(kColmap) + " model_converter --input_path '" + dir.string() +
                              "' --output_path '" + binary.string() + "' --output_type BIN > /dev/null 2>&1";
  ASSERT_EQ(std::system(convert.c_str()), 0) << convert;
  ASSERT_TRUE(fs::exists(binary / "points3D.bin"));
  for (const fs::path& model : {dir, binary}) {
    const AnalyzerCounts colmap = RunModelAnalyzer(model);
    EXPECT_EQ(colmap.images, static_cast<long long>(counts.images)) << model << colmap.output;
    EXPECT_EQ(colmap.registered, static_cast<long long>(counts.images)) << model << colmap.output;
    EXPECT_EQ(colmap.points, static_cast<long long>(counts.points)) << model << colmap.output;
    EXPECT_EQ(colmap.observations, static_cast<long long>(counts.observations)) << model << colmap.output;
  }
}

TEST(ColmapExport, RandomMapRoundTripsThroughTheTextFiles) {
  const fs::path dir = testing::FreshTempDir("colmap_random") / "model";  // created by the export
  Map map = testing::RandomMap({});
  // A point nobody observes (a map may hold one between culling passes): left out.
  (void)map.AddPoint({1, 1, 1}, map.keyframes().handles()[0]);
  ASSERT_EQ(map.Validate(), "");
  const Calibration calibration = TestCalibration();
  const ColmapExportCounts counts = WriteColmapModel(map, calibration, dir);
  EXPECT_EQ(counts.points_left_out, 1u);
  EXPECT_GT(counts.observations, counts.points);
  ExpectModelMatchesMap(dir, map, calibration, counts);
  // Two agents: names carry the agent, so equal clocks of two agents cannot collide.
  const ColmapModel model = ReadModel(dir);
  EXPECT_EQ(model.images.at(1).name, "agent0/12345.png");
}

TEST(ColmapExport, AMinimumTrackLeavesShortTracksOut) {
  const fs::path dir = testing::FreshTempDir("colmap_min_track");
  const Map map = testing::RandomMap({});
  size_t long_tracks = 0, long_observations = 0;
  for (const MapPoint& p : map.points().values()) {
    if (p.observations.size() < 3) continue;
    ++long_tracks;
    long_observations += p.observations.size();
  }
  ASSERT_GT(long_tracks, 0u);
  ASSERT_LT(long_tracks, map.points().size());  // the test needs short tracks to leave out
  const ColmapExportCounts counts = WriteColmapModel(map, TestCalibration(), dir, 3);
  EXPECT_EQ(counts.points, long_tracks);
  EXPECT_EQ(counts.observations, long_observations);
  EXPECT_EQ(counts.points_left_out, map.points().size() - long_tracks);
  const ColmapModel model = ReadModel(dir);
  ASSERT_EQ(model.points.size(), long_tracks);
  // Every keypoint names an exported point or none; every exported point has 3 or more entries.
  size_t named = 0;
  for (const auto& [id, image] : model.images)
    for (const ColmapPoint2D& p : image.points2d) {
      if (p.point_id < 0) continue;
      ++named;
      EXPECT_TRUE(model.points.count(p.point_id)) << "image " << id << " names point " << p.point_id;
    }
  EXPECT_EQ(named, long_observations);
  for (const auto& [id, point] : model.points) EXPECT_GE(point.track.size(), 3u) << id;
}

TEST(ColmapExport, NamesAreTimestampsAndRepeatsGetTheKeyFrameId) {
  const fs::path dir = testing::FreshTempDir("colmap_names");
  testing::RandomMapOptions options;
  options.agents = 1;
  options.keyframes = 4;
  options.points = 50;
  options.erase_some = false;
  Map map = testing::RandomMap(options);
  map.keyframe(map.keyframes().handles()[2]).t_ns = map.keyframe(map.keyframes().handles()[1]).t_ns;
  (void)WriteColmapModel(map, TestCalibration(), dir);
  const ColmapModel model = ReadModel(dir);
  ASSERT_EQ(model.images.size(), 4u);
  EXPECT_EQ(model.images.at(1).name, "12345.png");
  EXPECT_EQ(model.images.at(2).name, "100012345.png");
  EXPECT_EQ(model.images.at(3).name, "100012345-kf2.png");
}

// Two keyframes looking down +z, three points projected exactly but for one keypoint 3-4-5 pixels off.
TEST(ColmapExport, ReprojectionErrorIsTheMeanPixelDistance) {
  const fs::path dir = testing::FreshTempDir("colmap_error");
  const Calibration calibration = TestCalibration();
  const PinholeCamera& cam = calibration.camera;
  Map map;
  std::vector<KeyFrameHandle> kfs;
  const std::vector<Eigen::Vector3d> world = {{0, 0, 10}, {1, -1, 8}, {-2, 0.5, 12}};
  for (int i = 0; i < 2; ++i) {
    KeyFrame kf;
    kf.t_ns = 1'000'000'000LL * (i + 1);
    kf.T_cam_world.translation() = Eigen::Vector3d(-0.5 * i, 0, 0);
    kf.resize(world.size() + 1);  // one keypoint without a point
    for (size_t k = 0; k < world.size(); ++k) {
      const Eigen::Vector3d x = kf.T_cam_world * world[k];
      kf.uv.mutable_data()[k] = Eigen::Vector2f(cam.fx * x.x() / x.z() + cam.cx, cam.fy * x.y() / x.z() + cam.cy);
    }
    kfs.push_back(map.AddKeyFrame(std::move(kf)));
  }
  map.keyframe(kfs[1]).uv.mutable_data()[0] += Eigen::Vector2f(3, 4);
  for (size_t k = 0; k < world.size(); ++k) {
    const PointHandle p = map.AddPoint(world[k], kfs[0]);
    for (KeyFrameHandle kf : kfs) map.AddObservation(p, kf, static_cast<uint32_t>(k));
  }
  const ColmapExportCounts counts = WriteColmapModel(map, calibration, dir);
  EXPECT_EQ(counts.images, 2u);
  EXPECT_EQ(counts.points, 3u);
  EXPECT_EQ(counts.observations, 6u);
  EXPECT_NEAR(counts.mean_reprojection_error_px, 2.5 / 3, 1e-3);
  const ColmapModel model = ReadModel(dir);
  EXPECT_NEAR(model.points.at(1).error, 2.5, 1e-3);
  EXPECT_NEAR(model.points.at(2).error, 0.0, 1e-3);
  EXPECT_EQ(model.images.at(1).points2d.back().point_id, -1);
  ExpectModelMatchesMap(dir, map, calibration, counts);
  if (!fs::exists(kColmap)) GTEST_SKIP() << kColmap << " not installed";
  ExpectColmapAgrees(dir, counts);
}

TEST(ColmapExport, SnapshotOfOneMapGoesIntoDirSeveralIntoSubfolders) {
  const fs::path root = testing::FreshTempDir("colmap_snapshot");
  LoadedSnapshot snapshot;
  snapshot.metadata.calibration = TestCalibration();
  snapshot.maps.push_back({.id = 3, .agents = {0}, .map = testing::RandomMap({})});
  std::vector<ColmapMapExport> exports = WriteColmapModels(snapshot, root / "one");
  ASSERT_EQ(exports.size(), 1u);
  EXPECT_EQ(exports[0].map_id, 3u);
  EXPECT_EQ(exports[0].dir, root / "one");
  EXPECT_TRUE(fs::exists(root / "one" / "points3D.txt"));

  testing::RandomMapOptions other;
  other.seed = 11;
  other.keyframes = 8;
  snapshot.maps.push_back({.id = 7, .agents = {0}, .map = testing::RandomMap(other)});
  exports = WriteColmapModels(snapshot, root / "two");
  ASSERT_EQ(exports.size(), 2u);
  EXPECT_FALSE(fs::exists(root / "two" / "images.txt"));
  for (size_t m = 0; m < 2; ++m) {
    const fs::path expected = root / "two" / std::to_string(snapshot.maps[m].id);
    EXPECT_EQ(exports[m].dir, expected);
    EXPECT_EQ(exports[m].map_id, snapshot.maps[m].id);
    ExpectModelMatchesMap(expected, snapshot.maps[m].map, snapshot.metadata.calibration, exports[m].counts);
  }
  if (!fs::exists(kColmap)) GTEST_SKIP() << kColmap << " not installed";
  for (const ColmapMapExport& e : exports) ExpectColmapAgrees(e.dir, e.counts);
}

TEST(ColmapExport, ColmapReadsTheRandomMapWithTheSameCounts) {
  if (!fs::exists(kColmap)) GTEST_SKIP() << kColmap << " not installed";
  const fs::path dir = testing::FreshTempDir("colmap_analyzer");
  Map map = testing::RandomMap({});
  (void)map.AddPoint({1, 1, 1}, map.keyframes().handles()[0]);
  const ColmapExportCounts counts = WriteColmapModel(map, TestCalibration(), dir);
  ExpectColmapAgrees(dir, counts);
}

TEST(ColmapExport, UnwritableDirectoryOrBadCameraIsAnErrorNamingThePath) {
  const fs::path root = testing::FreshTempDir("colmap_errors");
  std::ofstream(root / "blocker") << "a file, not a directory\n";
  const Map map = testing::RandomMap({});
  const fs::path below_file = root / "blocker" / "model";
  try {
    (void)WriteColmapModel(map, TestCalibration(), below_file);
    ADD_FAILURE() << "no error for " << below_file;
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find(below_file.string()), std::string::npos) << e.what();
  }
  try {
    (void)WriteColmapModel(map, TestCalibration(), root / "blocker");
    ADD_FAILURE() << "no error for a file in place of the directory";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find((root / "blocker").string()), std::string::npos) << e.what();
  }
  try {
    (void)WriteColmapModel(map, Calibration{}, root / "no_camera");
    ADD_FAILURE() << "no error for an invalid camera";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("camera"), std::string::npos) << e.what();
  }
  EXPECT_FALSE(fs::exists(root / "no_camera"));
  EXPECT_THROW((void)WriteColmapModels(LoadedSnapshot{}, root / "empty"), Error);
}

}  // namespace
}  // namespace flatslam
