// Map snapshots: round trip of a SLAM-built map and of random maps (every field and edge), byte
// identity on re-save, atomic save, and bad input (missing, truncated, flipped, wrong type, newer
// version, other vocabulary, out-of-range indices), each a flatslam::Error naming the problem.
#include "storage/snapshot.h"

#include <sys/stat.h>
#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>
#include <functional>
#include <string>

#include <flatbuffers/flatbuffers.h>
#include <gtest/gtest.h>

#include "core/error.h"
#include "flatslam/schemas/map_generated.h"
#include "jobs/slam_runner.h"
#include "storage/random_map.h"
#include "merge/map_merge.h"
#include "test_data.h"

namespace flatslam {
namespace {

namespace fs = std::filesystem;

std::vector<uint8_t> ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(in), {});
}

void WriteBytes(const fs::path& path, std::span<const uint8_t> bytes) {
  std::ofstream out(path, std::ios::binary);
  out.write(reinterpret_cast<const char*>(bytes.data()), static_cast<std::streamsize>(bytes.size()));
}

// Runs fn and returns the flatslam::Error message; fails the test when nothing is thrown.
std::string ErrorOf(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const Error& e) {
    return e.what();
  }
  ADD_FAILURE() << "no flatslam::Error thrown";
  return {};
}

bool Contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

SnapshotMetadata TestMetadata(uint64_t vocabulary = 0) {
  SnapshotMetadata m;
  m.calibration.sensor = Sensor::kStereo;
  m.calibration.camera = {458.654, 457.296, 367.215, 248.375, 752, 480};
  m.calibration.baseline_m = 0.110074;
  m.calibration.frame_rate_hz = 20;
  m.calibration.T_body_cam.translation() = Eigen::Vector3d(0.1, -0.2, 0.3);
  m.scales = {1.2f, 8};
  m.vocabulary_checksum = vocabulary;
  return m;
}

// Dense index of a keyframe handle, or kNoIndex when null or erased.
uint32_t KfIndex(const Map& map, KeyFrameHandle h) {
  return map.keyframes().contains(h) ? static_cast<uint32_t>(map.keyframes().dense_index(h)) : kNoIndex;
}
uint32_t PointIndex(const Map& map, PointHandle h) {
  return map.points().contains(h) ? static_cast<uint32_t>(map.points().dense_index(h)) : kNoIndex;
}

// Every field of every keyframe and point, handles compared through dense indices.
void ExpectSameMap(const Map& a, const Map& b) {
  ASSERT_EQ(a.keyframes().size(), b.keyframes().size());
  ASSERT_EQ(a.points().size(), b.points().size());
  for (size_t i = 0; i < a.keyframes().size(); ++i) {
    const KeyFrame& x = a.keyframes().values()[i];
    const KeyFrame& y = b.keyframes().values()[i];
    SCOPED_TRACE("keyframe " + std::to_string(i));
    EXPECT_EQ(x.id, y.id);
    EXPECT_EQ(x.frame_index, y.frame_index);
    EXPECT_EQ(x.t_ns, y.t_ns);
    EXPECT_EQ(x.agent, y.agent);
    EXPECT_TRUE(x.T_cam_world.matrix() == y.T_cam_world.matrix());
    ASSERT_EQ(x.size(), y.size());
    EXPECT_EQ(x.uv, y.uv);
    EXPECT_EQ(x.right_u, y.right_u);
    EXPECT_EQ(x.depth, y.depth);
    EXPECT_EQ(x.angle, y.angle);
    EXPECT_EQ(x.octave, y.octave);
    EXPECT_EQ(x.descriptor, y.descriptor);
    for (size_t k = 0; k < x.size(); ++k) ASSERT_EQ(PointIndex(a, x.points[k]), PointIndex(b, y.points[k])) << k;
    EXPECT_EQ(KfIndex(a, x.parent), KfIndex(b, y.parent));
    ASSERT_EQ(x.children.size(), y.children.size());
    for (size_t c = 0; c < x.children.size(); ++c) EXPECT_EQ(KfIndex(a, x.children[c]), KfIndex(b, y.children[c]));
    ASSERT_EQ(x.loop_edges.size(), y.loop_edges.size());
    for (size_t c = 0; c < x.loop_edges.size(); ++c)
      EXPECT_EQ(KfIndex(a, x.loop_edges[c]), KfIndex(b, y.loop_edges[c]));
    ASSERT_EQ(x.covisible.size(), y.covisible.size());
    for (size_t c = 0; c < x.covisible.size(); ++c) {
      EXPECT_EQ(KfIndex(a, x.covisible[c].first), KfIndex(b, y.covisible[c].first));
      EXPECT_EQ(x.covisible[c].second, y.covisible[c].second);
    }
  }
  for (size_t i = 0; i < a.points().size(); ++i) {
    const MapPoint& x = a.points().values()[i];
    const MapPoint& y = b.points().values()[i];
    SCOPED_TRACE("point " + std::to_string(i));
    EXPECT_TRUE(x.position == y.position);
    EXPECT_TRUE(x.normal == y.normal);
    EXPECT_EQ(x.descriptor, y.descriptor);
    EXPECT_EQ(x.min_distance, y.min_distance);
    EXPECT_EQ(x.max_distance, y.max_distance);
    EXPECT_EQ(KfIndex(a, x.reference), KfIndex(b, y.reference));
    EXPECT_EQ(x.first_keyframe_id, y.first_keyframe_id);
    EXPECT_EQ(x.visible, y.visible);
    EXPECT_EQ(x.found, y.found);
    ASSERT_EQ(x.observations.size(), y.observations.size());
    for (size_t o = 0; o < x.observations.size(); ++o) {
      EXPECT_EQ(KfIndex(a, x.observations[o].keyframe), KfIndex(b, y.observations[o].keyframe));
      EXPECT_EQ(x.observations[o].keypoint, y.observations[o].keypoint);
    }
  }
}

void ExpectSameCalibration(const Calibration& a, const Calibration& b) {
  EXPECT_EQ(a.sensor, b.sensor);
  EXPECT_EQ(a.camera.fx, b.camera.fx);
  EXPECT_EQ(a.camera.fy, b.camera.fy);
  EXPECT_EQ(a.camera.cx, b.camera.cx);
  EXPECT_EQ(a.camera.cy, b.camera.cy);
  EXPECT_EQ(a.camera.width, b.camera.width);
  EXPECT_EQ(a.camera.height, b.camera.height);
  EXPECT_EQ(a.baseline_m, b.baseline_m);
  EXPECT_EQ(a.frame_rate_hz, b.frame_rate_hz);
  EXPECT_TRUE(a.T_body_cam.matrix() == b.T_body_cam.matrix());
}

TEST(MapSnapshot, SlamMapRoundTripsExactly) {
  const auto dir = testing::FreshTempDir("snapshot_slam");
  const auto dataset = OpenDataset("synth:room:duration=8,width=480,height=360");
  SlamOptions options;
  SlamRunOptions run;
  run.deterministic = true;
  Map original;
  SnapshotMetadata metadata;
  metadata.calibration = dataset->calibration();
  run.on_finished = [&](const SlamSession& slam) {
    original = slam.map();
    const SnapshotMapRef ref{0, &slam.map()};
    SaveMapSnapshot(dir / "room.fsmap", {&ref, 1}, metadata);
  };
  const SlamRunResult result = RunSlam(*dataset, options, run);
  ASSERT_GT(original.keyframes().size(), 3u);
  ASSERT_GT(original.points().size(), 100u);
  ASSERT_EQ(original.Validate(), "");
  size_t with_children = 0, with_covisible = 0;
  for (const KeyFrame& kf : original.keyframes().values()) {
    with_children += !kf.children.empty();
    with_covisible += !kf.covisible.empty();
  }
  EXPECT_GT(with_children, 0u);
  EXPECT_GT(with_covisible, 0u);

  LoadedSnapshot loaded = LoadMapSnapshot(dir / "room.fsmap");
  EXPECT_EQ(loaded.format_version, kMapSnapshotFormatVersion);
  ExpectSameCalibration(loaded.metadata.calibration, metadata.calibration);
  ASSERT_EQ(loaded.maps.size(), 1u);
  EXPECT_EQ(loaded.maps[0].map.Validate(), "");
  ExpectSameMap(original, loaded.maps[0].map);

  const SnapshotMapRef again{0, &loaded.maps[0].map};
  SaveMapSnapshot(dir / "again.fsmap", {&again, 1}, loaded.metadata);
  EXPECT_EQ(ReadBytes(dir / "room.fsmap"), ReadBytes(dir / "again.fsmap"));
  fs::remove_all(dir);
}

TEST(MapSnapshot, RandomMapsRoundTripWithMetadataAndAgents) {
  testing::RandomMapOptions o;
  const Map a = testing::RandomMap(o);
  o.seed = 11;
  o.keyframes = 9;
  o.agents = 1;
  const Map b = testing::RandomMap(o);
  const Map empty;
  ASSERT_EQ(a.Validate(), "");
  const SnapshotMapRef refs[] = {{4, &a}, {9, &b}, {12, &empty}};
  const SnapshotMetadata metadata = TestMetadata(0xfeedfacecafebeefull);
  const std::vector<uint8_t> bytes = SerializeMapSnapshot(refs, metadata);

  const MapSnapshotView view = MapSnapshotView::FromBytes(bytes, "memory");
  EXPECT_EQ(view.map_count(), 3u);
  EXPECT_EQ(view.vocabulary_checksum(), 0xfeedfacecafebeefull);
  EXPECT_EQ(view.map_id(1), 9u);
  EXPECT_EQ(std::vector<uint32_t>(view.agents(0).begin(), view.agents(0).end()), (std::vector<uint32_t>{0, 1}));
  EXPECT_EQ(view.agents(1).size(), 1u);
  EXPECT_EQ(view.keyframe_count(0), a.keyframes().size());
  EXPECT_EQ(view.point_count(0), a.points().size());
  EXPECT_EQ(view.keyframe_count(2), 0u);
  EXPECT_TRUE(view.bounds(2).empty);
  const BoundingBox box = view.bounds(0);
  for (const MapPoint& p : a.points().values()) {
    EXPECT_TRUE((p.position.array() >= box.min.array()).all());
    EXPECT_TRUE((p.position.array() <= box.max.array()).all());
  }
  const Trajectory trajectory = view.KeyFrameTrajectory(0);
  ASSERT_EQ(trajectory.size(), a.keyframes().size());
  for (size_t i = 1; i < trajectory.size(); ++i) EXPECT_LT(trajectory[i - 1].t_ns, trajectory[i].t_ns);

  const LoadedSnapshot loaded = LoadMapSnapshotFromBytes(bytes, "memory");
  ExpectSameCalibration(loaded.metadata.calibration, metadata.calibration);
  EXPECT_EQ(loaded.metadata.scales.scale_factor, 1.2f);
  EXPECT_EQ(loaded.metadata.scales.levels, 8);
  ASSERT_EQ(loaded.maps.size(), 3u);
  EXPECT_EQ(loaded.maps[0].id, 4u);
  EXPECT_EQ(loaded.maps[2].id, 12u);
  ExpectSameMap(a, loaded.maps[0].map);
  ExpectSameMap(b, loaded.maps[1].map);
  for (const LoadedMap& m : loaded.maps) EXPECT_EQ(m.map.Validate(), "");
  // New keyframes in a loaded map continue the id sequence.
  Map continued = loaded.maps[0].map;
  uint64_t max_id = 0;
  for (const KeyFrame& kf : continued.keyframes().values()) max_id = std::max(max_id, kf.id);
  KeyFrame fresh;
  const KeyFrameHandle h = continued.AddKeyFrame(std::move(fresh));
  EXPECT_EQ(continued.keyframe(h).id, max_id + 1);

  const SnapshotMapRef again[] = {{4, &loaded.maps[0].map}, {9, &loaded.maps[1].map}, {12, &loaded.maps[2].map}};
  EXPECT_EQ(SerializeMapSnapshot(again, loaded.metadata), bytes);
}

// A checkpoint's copy of a map serializes exactly like the map: assigned over a copy of another
// map (with the same keyframe ids), then again after the source lost and gained keyframes.
TEST(MapSnapshot, SnapshotCopySerializesLikeItsSource) {
  testing::RandomMapOptions o;
  Map source = testing::RandomMap(o);
  o.seed = 3;
  o.keyframes = 25;
  Map copy = testing::RandomMap(o);
  const SnapshotMetadata metadata = TestMetadata(1);
  const SnapshotMapRef a{0, &source}, b{0, &copy};
  for (int round = 0; round < 3; ++round) {
    copy.AssignForSnapshot(source);
    EXPECT_EQ(copy.Validate(), "");
    EXPECT_EQ(SerializeMapSnapshot({&b, 1}, metadata), SerializeMapSnapshot({&a, 1}, metadata)) << "round " << round;
    // The copy shares every keyframe's measured columns with the source instead of copying them.
    for (KeyFrameHandle h : source.keyframes().handles()) {
      EXPECT_TRUE(copy.keyframe(h).uv.shares_with(source.keyframe(h).uv));
      EXPECT_TRUE(copy.keyframe(h).descriptor.shares_with(source.keyframe(h).descriptor));
      EXPECT_FALSE(copy.keyframe(h).points.data() == source.keyframe(h).points.data());
    }
    // The source moves on: a keyframe goes (the last one moves into its dense position), one
    // comes, and a point changes.
    source.EraseKeyFrame(source.keyframes().handles()[2 + round]);
    KeyFrame fresh = source.keyframes().values()[0];
    fresh.points.assign(fresh.size(), PointHandle::null());
    fresh.covisible.clear();
    fresh.children.clear();
    fresh.loop_edges.clear();
    fresh.parent = KeyFrameHandle::null();
    const Eigen::Vector2f first = source.keyframes().values()[0].uv[0];
    fresh.uv.mutable_data()[0].x() += 1.0f;  // a shared column is copied before it is written
    EXPECT_EQ(source.keyframes().values()[0].uv[0], first);
    EXPECT_FALSE(fresh.uv.shares_with(source.keyframes().values()[0].uv));
    (void)source.AddKeyFrame(std::move(fresh));
    source.points().values()[0].position.x() += 1.0;
    ASSERT_EQ(source.Validate(), "");
  }
}

// An RGB-D map records the virtual baseline of its keyframes' right_u (map merge needs it).
TEST(MapSnapshot, RgbdVirtualBaselineIsRecorded) {
  testing::RandomMapOptions o;
  o.keyframes = 5;
  const Map map = testing::RandomMap(o);
  SnapshotMetadata metadata = TestMetadata(2);
  metadata.calibration.sensor = Sensor::kRgbd;
  metadata.rgbd_virtual_baseline_m = 0.125;
  const SnapshotMapRef ref{0, &map};
  const std::vector<uint8_t> bytes = SerializeMapSnapshot({&ref, 1}, metadata);
  EXPECT_EQ(MapSnapshotView::FromBytes(bytes, "memory").rgbd_virtual_baseline_m(), 0.125);
  EXPECT_EQ(LoadMapSnapshotFromBytes(bytes, "memory").metadata.rgbd_virtual_baseline_m, 0.125);
  const MergeCamera camera = MergeCamera::FromCalibration(metadata.calibration, metadata.scales, 0.125);
  EXPECT_DOUBLE_EQ(camera.geometry.bf, 0.125 * metadata.calibration.camera.fx);
  EXPECT_THROW((void)MergeCamera::FromCalibration(metadata.calibration, metadata.scales, 0), Error);
}

// A monocular map whose session refined its camera records the refinement (a session continuing
// it sees the dataset through it); a map without one reads back the camera as given.
TEST(MapSnapshot, ARefinedCameraIsRecorded) {
  testing::RandomMapOptions o;
  o.keyframes = 5;
  const Map map = testing::RandomMap(o);
  SnapshotMetadata metadata = TestMetadata(2);
  const SnapshotMapRef ref{0, &map};
  const std::vector<uint8_t> plain = SerializeMapSnapshot({&ref, 1}, metadata);
  EXPECT_FALSE(MapSnapshotView::FromBytes(plain, "memory").camera_refit().refined());
  metadata.camera_refit = CameraRefit{1.0042, 0.0153};
  const std::vector<uint8_t> bytes = SerializeMapSnapshot({&ref, 1}, metadata);
  const CameraRefit view = MapSnapshotView::FromBytes(bytes, "memory").camera_refit();
  EXPECT_EQ(view.focal_scale, 1.0042);
  EXPECT_EQ(view.k1, 0.0153);
  const CameraRefit loaded = LoadMapSnapshotFromBytes(bytes, "memory").metadata.camera_refit;
  EXPECT_EQ(loaded.focal_scale, 1.0042);
  EXPECT_EQ(loaded.k1, 0.0153);
  // The camera the session was given before the refinement comes back with the size of the
  // calibration; a snapshot that does not record it reads fx 0.
  EXPECT_EQ(MapSnapshotView::FromBytes(bytes, "memory").given_camera().fx, 0);
  metadata.given_camera = PinholeCamera{701.5, 702.5, 600.25, 180.75, 0, 0};
  const std::vector<uint8_t> with_given = SerializeMapSnapshot({&ref, 1}, metadata);
  const PinholeCamera given = LoadMapSnapshotFromBytes(with_given, "memory").metadata.given_camera;
  EXPECT_EQ(given.fx, 701.5);
  EXPECT_EQ(given.fy, 702.5);
  EXPECT_EQ(given.cx, 600.25);
  EXPECT_EQ(given.cy, 180.75);
  EXPECT_EQ(given.width, metadata.calibration.camera.width);
  EXPECT_EQ(given.height, metadata.calibration.camera.height);
}

// A checkpoint's session (next frame, dataset, command line, trajectory anchored at keyframes)
// comes back from the file with handles of the loaded map.
TEST(MapSnapshot, SessionRoundTrips) {
  testing::RandomMapOptions o;
  const Map map = testing::RandomMap(o);
  SnapshotMetadata metadata = TestMetadata(5);
  SnapshotSession session;
  session.next_frame = 1234;
  session.dataset = "synth:room";
  session.arguments = {"synth:room", "--out=/tmp/x", "--checkpoint-every=2"};
  session.global_adjustment_pending = true;
  const auto handles = map.keyframes().handles();
  for (size_t i = 0; i < 40; ++i) {
    AnchoredFramePose f;
    f.t_ns = 1000 + static_cast<int64_t>(i);
    f.reference = i % 7 == 3 ? KeyFrameHandle::null() : handles[i % handles.size()];
    f.T_cam_ref = CompactPose(
        Eigen::Isometry3d(Eigen::Translation3d(0.1 * i, 0, 1) * Eigen::AngleAxisd(0.01 * i, Eigen::Vector3d::UnitY())));
    f.T_cam_world = CompactPose(
        Eigen::Isometry3d(Eigen::Translation3d(0, 0.2 * i, 0) * Eigen::AngleAxisd(0.02 * i, Eigen::Vector3d::UnitZ())));
    session.frames.push_back(f);
  }
  metadata.session = session;
  const SnapshotMapRef ref{0, &map};
  const std::vector<uint8_t> bytes = SerializeMapSnapshot({&ref, 1}, metadata);
  const MapSnapshotView view = MapSnapshotView::FromBytes(bytes, "memory");
  ASSERT_TRUE(view.session_summary().has_value());
  EXPECT_EQ(view.session_summary()->next_frame, 1234u);
  EXPECT_EQ(view.session_summary()->arguments, session.arguments);
  EXPECT_EQ(view.session_frame_count(), 40u);
  const LoadedSnapshot loaded = LoadMapSnapshotFromBytes(bytes, "memory");
  ASSERT_TRUE(loaded.metadata.session.has_value());
  const SnapshotSession& back = *loaded.metadata.session;
  EXPECT_EQ(back.dataset, "synth:room");
  EXPECT_TRUE(back.global_adjustment_pending);
  ASSERT_EQ(back.frames.size(), 40u);
  const Map& loaded_map = loaded.maps[0].map;
  for (size_t i = 0; i < 40; ++i) {
    const AnchoredFramePose& f = back.frames[i];
    EXPECT_EQ(f.t_ns, session.frames[i].t_ns);
    if (session.frames[i].reference.is_null()) {
      EXPECT_TRUE(f.reference.is_null());
    } else {
      // The same keyframe: dense positions are kept by a load.
      EXPECT_EQ(loaded_map.keyframes().dense_index(f.reference),
                map.keyframes().dense_index(session.frames[i].reference));
    }
    // Stored as given: bit for bit.
    EXPECT_EQ(std::memcmp(&f.T_cam_ref, &session.frames[i].T_cam_ref, sizeof(CompactPose)), 0);
    EXPECT_EQ(std::memcmp(&f.T_cam_world, &session.frames[i].T_cam_world, sizeof(CompactPose)), 0);
  }
  metadata.session->global_adjustment_pending = false;
  EXPECT_FALSE(MapSnapshotView::FromBytes(SerializeMapSnapshot({&ref, 1}, metadata), "memory")
                   .session_summary()
                   ->global_adjustment_pending);
  // A plain map snapshot has no session.
  EXPECT_FALSE(MapSnapshotView::FromBytes(SerializeMapSnapshot({&ref, 1}, TestMetadata(5)), "plain").session_summary());
}

class MapSnapshotBadInput : public ::testing::Test {
 protected:
  void SetUp() override {
    testing::RandomMapOptions o;
    o.keyframes = 8;
    o.points = 120;
    o.keypoints = 80;
    map_ = testing::RandomMap(o);
    const SnapshotMapRef ref{0, &map_};
    bytes_ = SerializeMapSnapshot({&ref, 1}, TestMetadata(42));
  }
  Map map_;
  std::vector<uint8_t> bytes_;
};

TEST_F(MapSnapshotBadInput, MissingFile) {
  const auto dir = testing::FreshTempDir("snapshot_missing");
  const std::string e = ErrorOf([&] { (void)LoadMapSnapshot(dir / "none.fsmap"); });
  EXPECT_TRUE(Contains(e, "none.fsmap")) << e;
  EXPECT_TRUE(Contains(e, "cannot open")) << e;
  fs::remove_all(dir);
}

TEST_F(MapSnapshotBadInput, TruncatedAtEveryLength) {
  size_t checked = 0;
  for (size_t len = 0; len < bytes_.size(); len += (len < 256 ? 1 : 97)) {
    const std::span<const uint8_t> cut(bytes_.data(), len);
    const std::string e = ErrorOf([&] { (void)LoadMapSnapshotFromBytes(cut, "cut.fsmap"); });
    ASSERT_TRUE(Contains(e, "cut.fsmap")) << len << ": " << e;
    ASSERT_TRUE(Contains(e, "truncated") || Contains(e, "corrupt") || Contains(e, "not a flatslam map"))
        << len << ": " << e;
    // Without the content hash, structure checks alone still refuse every cut.
    SnapshotReadOptions quick;
    quick.verify_content_hash = false;
    (void)ErrorOf([&] { (void)MapSnapshotView::FromBytes(cut, "cut.fsmap", quick); });
    ++checked;
  }
  EXPECT_GT(checked, 300u);
}

TEST_F(MapSnapshotBadInput, FlippedBytesAnywhere) {
  SnapshotReadOptions quick;
  quick.verify_content_hash = false;
  size_t checked = 0;
  for (size_t pos = 0; pos < bytes_.size(); pos += (pos < 512 ? 1 : 13)) {
    for (uint8_t mask : {uint8_t{0x01}, uint8_t{0x80}, uint8_t{0xff}}) {
      std::vector<uint8_t> bad = bytes_;
      bad[pos] ^= mask;
      const std::string e = ErrorOf([&] { (void)LoadMapSnapshotFromBytes(bad, "flip.fsmap"); });
      ASSERT_TRUE(Contains(e, "flip.fsmap")) << pos << ": " << e;
      // Structure-only checks may accept a changed value, but must never crash or read out of bounds.
      try {
        const MapSnapshotView view = MapSnapshotView::FromBytes(bad, "flip.fsmap", quick);
        for (size_t m = 0; m < view.map_count(); ++m) (void)view.bounds(m), (void)view.KeyFrameTrajectory(m);
      } catch (const Error&) {
      }
      ++checked;
    }
  }
  EXPECT_GT(checked, 1500u);
}

TEST_F(MapSnapshotBadInput, WrongFileType) {
  const auto dir = testing::FreshTempDir("snapshot_type");
  const uint8_t png[] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n', 0, 0, 0, 13, 'I', 'H', 'D',
                         'R',  0,   0,   0,   1,    0,    0,    0,    1, 8, 0, 0,  0,   0};
  WriteBytes(dir / "image.png", png);
  std::string e = ErrorOf([&] { (void)LoadMapSnapshot(dir / "image.png"); });
  EXPECT_TRUE(Contains(e, "image.png")) << e;
  EXPECT_TRUE(Contains(e, "not a flatslam map snapshot")) << e;
  const std::string text = "# TUM trajectory\n1.0 0 0 0 0 0 0 1\n";
  WriteBytes(dir / "notes.txt", {reinterpret_cast<const uint8_t*>(text.data()), text.size()});
  e = ErrorOf([&] { (void)MapSnapshotView::Open(dir / "notes.txt"); });
  EXPECT_TRUE(Contains(e, "not a flatslam map snapshot")) << e;
  WriteBytes(dir / "empty.fsmap", {});
  e = ErrorOf([&] { (void)MapSnapshotView::Open(dir / "empty.fsmap"); });
  EXPECT_TRUE(Contains(e, "0 bytes")) << e;
  e = ErrorOf([&] { (void)MapSnapshotView::Open(dir); });
  EXPECT_TRUE(Contains(e, "not a regular file")) << e;
  fs::remove_all(dir);
}

// Builds a small valid snapshot by hand (2 keyframes, 2 points); edit changes fields to make it bad.
struct Crafted {
  uint32_t version = kMapSnapshotFormatVersion;
  uint32_t point_index = 0;  // keyframe 0 keypoint 0
  uint32_t parent = 0;       // of keyframe 1
  uint32_t child = 1;        // of keyframe 0
  uint32_t covisible = 1;    // of keyframe 0
  uint32_t loop = kNoIndex;  // of keyframe 0, none
  uint32_t reference = 0;    // of point 0
  uint32_t observation_keyframe = 0;
  uint32_t observation_keypoint = 0;
  uint32_t last_offset = 2;
  uint32_t agent = 0;
  size_t depth_size = 2;  // keyframe 0's depth column
};

std::vector<uint8_t> Craft(const Crafted& c) {
  namespace s = schema;
  flatbuffers::FlatBufferBuilder b;
  const double identity_matrix[12] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0};
  const s::Pose34 identity{flatbuffers::span<const double, 12>(identity_matrix)};
  std::vector<flatbuffers::Offset<s::KeyFrameRecord>> kfs;
  for (uint32_t k = 0; k < 2; ++k) {
    const std::vector<s::Vec2f> uv = {{1, 2}, {3, 4}};
    const std::vector<float> scalars = {1, 2};
    const std::vector<float> depth(k == 0 ? c.depth_size : 2, 1.0f);
    const std::vector<uint8_t> octave = {0, 1};
    const std::vector<s::Descriptor256> desc(2);
    const std::vector<uint32_t> points =
        k == 0 ? std::vector<uint32_t>{c.point_index, kNoIndex} : std::vector<uint32_t>{1, kNoIndex};
    const std::vector<uint32_t> children = k == 0 ? std::vector<uint32_t>{c.child} : std::vector<uint32_t>{};
    std::vector<uint32_t> loops;
    if (k == 0 && c.loop != kNoIndex) loops.push_back(c.loop);
    const std::vector<s::CovisibilityEdge> covis = {{k == 0 ? c.covisible : 0, 1}};
    const auto off =
        s::CreateKeyFrameRecordDirect(b, k, k, k * 1000, c.agent, &identity, k == 0 ? kNoIndex : c.parent, &children,
                                      &covis, &loops, &uv, &scalars, &depth, &scalars, &octave, &desc, &points);
    kfs.push_back(off);
  }
  std::vector<s::PointRecord> points(2);
  points[0] = s::PointRecord(s::Vec3d(1, 2, 3), s::Vec3d(0, 0, 1), s::Descriptor256(), 0, 1, 2, c.reference, 1, 1);
  points[1] = s::PointRecord(s::Vec3d(4, 5, 6), s::Vec3d(0, 0, 1), s::Descriptor256(), 1, 1, 2, 1, 1, 1);
  const std::vector<uint32_t> offsets = {0, 1, c.last_offset};
  const std::vector<s::ObservationRecord> observations = {{c.observation_keyframe, c.observation_keypoint}, {1, 0}};
  const std::vector<uint32_t> agents = {0};
  const auto segment = s::CreateMapSegmentDirect(b, 0, &agents, &kfs, &points, &offsets, &observations);
  const std::vector<flatbuffers::Offset<s::MapSegment>> segments = {segment};
  const auto calibration = s::CreateCalibration(b, s::Sensor::Stereo, 500, 500, 320, 240, 640, 480, 0.1, 10, &identity);
  const auto scales = s::CreateScalePyramid(b, 1.2f, 8);
  const s::ContentHash zero(0);
  b.Finish(s::CreateMapSnapshotDirect(b, c.version, &zero, 0, calibration, scales, &segments), "FSMP");
  std::vector<uint8_t> bytes(b.GetBufferPointer(), b.GetBufferPointer() + b.GetSize());
  const size_t hash_at =
      reinterpret_cast<const uint8_t*>(s::GetMapSnapshot(bytes.data())->content_hash()) - bytes.data();
  const uint64_t hash = SnapshotHash(bytes, hash_at, 8);
  std::memcpy(bytes.data() + hash_at, &hash, 8);
  return bytes;
}

TEST(MapSnapshotCrafted, ValidCraftLoads) {
  const LoadedSnapshot loaded = LoadMapSnapshotFromBytes(Craft({}), "craft.fsmap");
  ASSERT_EQ(loaded.maps.size(), 1u);
  EXPECT_EQ(loaded.maps[0].map.keyframes().size(), 2u);
  EXPECT_EQ(loaded.maps[0].map.points().size(), 2u);
}

TEST(MapSnapshotCrafted, NewerVersionIsNamed) {
  Crafted c;
  c.version = kMapSnapshotFormatVersion + 1;
  const std::string e = ErrorOf([&] { (void)LoadMapSnapshotFromBytes(Craft(c), "future.fsmap"); });
  EXPECT_TRUE(Contains(e, "future.fsmap")) << e;
  EXPECT_TRUE(Contains(e, "newer")) << e;
  EXPECT_TRUE(Contains(e, "format version " + std::to_string(kMapSnapshotFormatVersion + 1))) << e;
}

TEST(MapSnapshotCrafted, OutOfRangeIndicesAreNamed) {
  const std::vector<std::pair<std::function<void(Crafted&)>, std::string>> cases = {
      {[](Crafted& c) { c.point_index = 2; }, "point index 2 out of range"},
      {[](Crafted& c) { c.point_index = 1000000; }, "point index 1000000 out of range"},
      {[](Crafted& c) { c.parent = 7; }, "parent index 7 out of range"},
      {[](Crafted& c) { c.child = 2; }, "child index 2 out of range"},
      {[](Crafted& c) { c.covisible = 5; }, "covisible keyframe index 5"},
      {[](Crafted& c) { c.loop = 9; }, "loop edge index 9"},
      {[](Crafted& c) { c.reference = 3; }, "reference keyframe index 3 out of range"},
      {[](Crafted& c) { c.observation_keyframe = 4; }, "keyframe index 4 out of range"},
      {[](Crafted& c) { c.observation_keypoint = 2; }, "keypoint 2 out of range"},
      {[](Crafted& c) { c.last_offset = 3; }, "observation offsets end at 3"},
      {[](Crafted& c) { c.last_offset = 0; }, "observation offsets decrease"},
      {[](Crafted& c) { c.agent = 5; }, "agent 5 missing"},
      {[](Crafted& c) { c.depth_size = 1; }, "keypoint columns differ in size"},
      // In range but inconsistent: keypoint 0 of keyframe 0 names point 1, which lacks that observation.
      {[](Crafted& c) { c.point_index = 1; }, "inconsistent"},
  };
  for (const auto& [edit, expected] : cases) {
    Crafted c;
    edit(c);
    const std::vector<uint8_t> bytes = Craft(c);
    const std::string e = ErrorOf([&] { (void)LoadMapSnapshotFromBytes(bytes, "bad.fsmap"); });
    EXPECT_TRUE(Contains(e, "bad.fsmap")) << e;
    EXPECT_TRUE(Contains(e, expected)) << "expected '" << expected << "' in: " << e;
  }
}

TEST_F(MapSnapshotBadInput, VocabularyMismatch) {
  SnapshotReadOptions options;
  options.vocabulary_checksum = 42;
  EXPECT_NO_THROW((void)LoadMapSnapshotFromBytes(bytes_, "voc.fsmap", options));
  options.vocabulary_checksum = 43;
  const std::string e = ErrorOf([&] { (void)LoadMapSnapshotFromBytes(bytes_, "voc.fsmap", options); });
  EXPECT_TRUE(Contains(e, "vocabulary checksum 42")) << e;
  EXPECT_TRUE(Contains(e, "43")) << e;
}

TEST_F(MapSnapshotBadInput, FailedSaveKeepsTheOldFileAndLeavesNoTemporary) {
  const auto dir = testing::FreshTempDir("snapshot_atomic");
  const SnapshotMapRef ref{0, &map_};
  const fs::path good = dir / "map.fsmap";
  SaveMapSnapshot(good, {&ref, 1}, TestMetadata(42));
  const std::vector<uint8_t> before = ReadBytes(good);
  EXPECT_EQ(before, bytes_);

  // A directory that does not exist.
  std::string e = ErrorOf([&] { SaveMapSnapshot(dir / "no" / "such" / "map.fsmap", {&ref, 1}, TestMetadata()); });
  EXPECT_TRUE(Contains(e, "cannot save map snapshot")) << e;
  // The target is a directory: writing succeeds, the rename fails, the temporary is removed.
  fs::create_directories(dir / "taken.fsmap" / "inside");
  e = ErrorOf([&] { SaveMapSnapshot(dir / "taken.fsmap", {&ref, 1}, TestMetadata()); });
  EXPECT_TRUE(Contains(e, "rename failed")) << e;
  // A read-only directory (root ignores permissions, so only checked for other users).
  if (::geteuid() != 0) {
    fs::permissions(dir, fs::perms::owner_read | fs::perms::owner_exec);
    e = ErrorOf([&] { SaveMapSnapshot(good, {&ref, 1}, TestMetadata(7)); });
    EXPECT_TRUE(Contains(e, "cannot create")) << e;
    fs::permissions(dir, fs::perms::owner_all);
  }
  EXPECT_EQ(ReadBytes(good), before);
  size_t entries = 0;
  for (const auto& entry : fs::directory_iterator(dir)) {
    ++entries;
    EXPECT_EQ(entry.path().filename().string().find(".tmp"), std::string::npos) << entry.path();
  }
  EXPECT_EQ(entries, 2u);  // map.fsmap and taken.fsmap/
  // A good save replaces the file.
  SaveMapSnapshot(good, {&ref, 1}, TestMetadata(7));
  EXPECT_EQ(MapSnapshotView::Open(good).vocabulary_checksum(), 7u);
  EXPECT_EQ(ReadBytes(good), SerializeMapSnapshot({&ref, 1}, TestMetadata(7)));
  fs::remove_all(dir);
}

// A file of several write chunks (8 MiB each, written while the rest is still being built), saved
// over an existing one: the bytes on disk are exactly the serialized snapshot, content hash included.
TEST(MapSnapshot, LargeSaveOverAnExistingFileIsByteExact) {
  testing::RandomMapOptions o;
  o.keyframes = 320;
  o.keypoints = 2000;
  o.points = 20000;
  const Map map = testing::RandomMap(o);
  const SnapshotMapRef ref{0, &map};
  const auto dir = testing::FreshTempDir("snapshot_large");
  const fs::path path = dir / "map.fsmap";
  SaveMapSnapshot(path, {&ref, 1}, TestMetadata(1));
  SaveMapSnapshot(path, {&ref, 1}, TestMetadata(2));
  const std::vector<uint8_t> expected = SerializeMapSnapshot({&ref, 1}, TestMetadata(2));
  ASSERT_GT(expected.size(), size_t{32} << 20);
  EXPECT_TRUE(ReadBytes(path) == expected);
  const MapSnapshotView view = MapSnapshotView::Open(path);  // checks the content hash
  EXPECT_EQ(view.vocabulary_checksum(), 2u);
  EXPECT_EQ(std::distance(fs::directory_iterator(dir), fs::directory_iterator()), 1);
  fs::remove_all(dir);
}

}  // namespace
}  // namespace flatslam
