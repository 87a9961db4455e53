// Conversions between the map's entities and their flatbuffers records (schemas/map.fbs), shared
// by map snapshots (snapshot.cc) and the agents' messages (keyframe_message.cc,
// correction_message.cc): one way to write a keyframe record and to read one back, and one set of
// checks before a message is read. Internal to src/storage.
// Concurrency: pure functions over the caller's data.
#pragma once

#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <vector>

#include <flatbuffers/flatbuffers.h>

#include "core/error.h"
#include "ecs/map.h"
#include "flatslam/schemas/map_generated.h"
#include "io/calibration.h"

namespace flatslam::records {

namespace fb = flatbuffers;

inline constexpr uint32_t kNone = 0xffffffffu;  // "no index" in a record

// The root of a message buffer after the checks every agent message gets: its file identifier,
// the flatbuffers verifier, and a format version from min_version to max_version. Throws flatslam::Error
// naming `what` (e.g. "keyframe message 12 from agent 1") and `kind` ("keyframe message").
template <class Root>
const Root& VerifiedMessage(std::span<const uint8_t> bytes, const char* identifier, uint32_t max_version,
                            const std::string& what, const char* kind, uint32_t min_version = 1) {
  FLATSLAM_CHECK(bytes.size() >= 8 && fb::BufferHasIdentifier(bytes.data(), identifier), what, ": not a ", kind, " (",
                 bytes.size(), " bytes)");
  fb::Verifier verifier(bytes.data(), bytes.size());
  FLATSLAM_CHECK(verifier.VerifyBuffer<Root>(identifier), what, ": corrupt (flatbuffers verification failed)");
  const Root& root = *fb::GetRoot<Root>(bytes.data());
  FLATSLAM_CHECK(root.format_version() >= min_version && root.format_version() <= max_version, what,
                 ": format version ", root.format_version(), " (this build reads ", min_version, " to ", max_version,
                 ")");
  return root;
}

static_assert(sizeof(schema::Vec2f) == sizeof(Eigen::Vector2f));
static_assert(sizeof(schema::Descriptor256) == sizeof(Descriptor));

template <class T>
size_t Size(const fb::Vector<T>* v) {
  return v ? v->size() : 0;
}
// Absent vectors read as empty.
template <class T>
std::span<const T> Span(const fb::Vector<T>* v) {
  return v ? std::span<const T>(v->data(), v->size()) : std::span<const T>();
}
template <class T>
std::span<const T> Span(const fb::Vector<const T*>* v) {
  return v ? std::span<const T>(reinterpret_cast<const T*>(v->Data()), v->size()) : std::span<const T>();
}

inline schema::Pose34 ToPose(const Eigen::Isometry3d& T) {
  double m[12];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) m[r * 4 + c] = T.matrix()(r, c);
  return schema::Pose34(fb::span<const double, 12>(m));
}
inline Eigen::Isometry3d FromPose(const schema::Pose34* pose) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  if (!pose) return T;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) T.matrix()(r, c) = pose->m()->Get(r * 4 + c);
  return T;
}
inline schema::Vec3d ToVec(const Eigen::Vector3d& v) {
  return schema::Vec3d(v.x(), v.y(), v.z());
}
inline Eigen::Vector3d FromVec(const schema::Vec3d& v) {
  return {v.x(), v.y(), v.z()};
}
inline schema::Descriptor256 ToDescriptor(const Descriptor& d) {
  return schema::Descriptor256(fb::span<const uint64_t, 4>(d.data(), 4));
}
inline Descriptor FromDescriptor(const schema::Descriptor256& d) {
  Descriptor out;
  for (int i = 0; i < 4; ++i) out[i] = d.w()->Get(i);
  return out;
}

inline fb::Offset<schema::Calibration> BuildCalibration(fb::FlatBufferBuilder& builder, const Calibration& calib) {
  const schema::Pose34 T_body_cam = ToPose(calib.T_body_cam);
  return schema::CreateCalibration(builder, static_cast<schema::Sensor>(calib.sensor), calib.camera.fx, calib.camera.fy,
                                   calib.camera.cx, calib.camera.cy, calib.camera.width, calib.camera.height,
                                   calib.baseline_m, calib.frame_rate_hz, &T_body_cam);
}
inline Calibration CalibrationFromRecord(const schema::Calibration& c) {
  Calibration out;
  out.sensor = static_cast<Sensor>(c.sensor());
  out.camera.fx = c.fx();
  out.camera.fy = c.fy();
  out.camera.cx = c.cx();
  out.camera.cy = c.cy();
  out.camera.width = c.width();
  out.camera.height = c.height();
  out.baseline_m = c.baseline_m();
  out.frame_rate_hz = c.frame_rate_hz();
  out.T_body_cam = FromPose(c.body_from_cam());
  return out;
}

// A point's record; `reference` is its reference keyframe's index (kNone: none).
inline schema::PointRecord ToPointRecord(const MapPoint& p, uint32_t reference) {
  return schema::PointRecord(ToVec(p.position), ToVec(p.normal), ToDescriptor(p.descriptor), p.first_keyframe_id,
                             p.min_distance, p.max_distance, reference, p.visible, p.found);
}
// A point from its record, without its reference keyframe and observations (the caller's).
inline MapPoint FromPointRecord(const schema::PointRecord& r) {
  MapPoint p;
  p.position = FromVec(r.position());
  p.normal = FromVec(r.normal());
  p.descriptor = FromDescriptor(r.descriptor());
  p.first_keyframe_id = r.first_keyframe_id();
  p.min_distance = r.min_distance();
  p.max_distance = r.max_distance();
  p.visible = r.visible();
  p.found = r.found();
  return p;
}

// Writes a keyframe's record: `point_index(PointHandle)` and `keyframe_index(KeyFrameHandle)`
// give the indices stored for its points and graph edges (kNone: dropped for edges, none for a
// point); with graph = false no edges are written. Every keypoint column has kf.size() entries.
template <class PointIndex, class KeyFrameIndex>
fb::Offset<schema::KeyFrameRecord> BuildKeyFrameRecord(fb::FlatBufferBuilder& builder, const KeyFrame& kf,
                                                       PointIndex&& point_index, KeyFrameIndex&& keyframe_index,
                                                       bool graph) {
  const size_t n = kf.size();
  const auto uv = builder.CreateVectorOfStructs(reinterpret_cast<const schema::Vec2f*>(kf.uv.data()), n);
  const auto right_u = builder.CreateVector(kf.right_u.vector());
  const auto depth = builder.CreateVector(kf.depth.vector());
  const auto angle = builder.CreateVector(kf.angle.vector());
  const auto octave = builder.CreateVector(kf.octave.vector());
  const auto descriptors =
      builder.CreateVectorOfStructs(reinterpret_cast<const schema::Descriptor256*>(kf.descriptor.data()), n);
  uint32_t* point_column = nullptr;
  const auto points = builder.CreateUninitializedVector<uint32_t>(n, &point_column);
  for (size_t k = 0; k < n; ++k) point_column[k] = point_index(kf.points[k]);
  fb::Offset<fb::Vector<uint32_t>> children, loop_edges;
  fb::Offset<fb::Vector<const schema::CovisibilityEdge*>> covisible;
  uint32_t parent = kNone;
  if (graph) {
    // Graph edges to erased keyframes carry no information: they are dropped.
    std::vector<uint32_t> indices;
    for (KeyFrameHandle c : kf.children)
      if (const uint32_t i = keyframe_index(c); i != kNone) indices.push_back(i);
    children = builder.CreateVector(indices);
    indices.clear();
    for (KeyFrameHandle l : kf.loop_edges)
      if (const uint32_t i = keyframe_index(l); i != kNone) indices.push_back(i);
    loop_edges = builder.CreateVector(indices);
    std::vector<schema::CovisibilityEdge> edges;
    for (const auto& [other, weight] : kf.covisible)
      if (const uint32_t i = keyframe_index(other); i != kNone) edges.emplace_back(i, weight);
    covisible = builder.CreateVectorOfStructs(edges);
    parent = keyframe_index(kf.parent);
  }
  schema::KeyFrameRecordBuilder record(builder);
  const schema::Pose34 pose = ToPose(kf.T_cam_world);
  record.add_id(kf.id);
  record.add_frame_index(kf.frame_index);
  record.add_t_ns(kf.t_ns);
  record.add_agent(kf.agent);
  record.add_cam_from_world(&pose);
  record.add_parent(parent);
  if (graph) {
    record.add_children(children);
    record.add_covisible(covisible);
    record.add_loop_edges(loop_edges);
  }
  record.add_uv(uv);
  record.add_right_u(right_u);
  record.add_depth(depth);
  record.add_angle(angle);
  record.add_octave(octave);
  record.add_descriptors(descriptors);
  record.add_points(points);
  return record.Finish();
}

// A keyframe's identity, pose and keypoint columns from a record whose columns have equal sizes
// (checked by the caller); its points are null and its graph empty.
inline KeyFrame KeyFrameFromRecord(const schema::KeyFrameRecord& r) {
  const size_t n = Size(r.uv());
  KeyFrame kf;
  kf.id = r.id();
  kf.frame_index = r.frame_index();
  kf.t_ns = r.t_ns();
  kf.agent = r.agent();
  kf.T_cam_world = FromPose(r.cam_from_world());
  std::vector<Eigen::Vector2f> uv(n);
  std::vector<Descriptor> descriptors(n);
  if (n > 0) {
    std::memcpy(static_cast<void*>(uv.data()), Span(r.uv()).data(), n * sizeof(Eigen::Vector2f));
    std::memcpy(descriptors.data(), Span(r.descriptors()).data(), n * sizeof(Descriptor));
  }
  kf.uv = std::move(uv);
  kf.descriptor = std::move(descriptors);
  const auto right_u = Span(r.right_u()), depth = Span(r.depth()), angle = Span(r.angle());
  const auto octave = Span(r.octave());
  kf.right_u.assign(right_u.begin(), right_u.end());
  kf.depth.assign(depth.begin(), depth.end());
  kf.angle.assign(angle.begin(), angle.end());
  kf.octave.assign(octave.begin(), octave.end());
  kf.points.assign(n, PointHandle::null());
  return kf;
}

// Whether every keypoint column of a record has the same size.
inline bool KeyFrameColumnsAgree(const schema::KeyFrameRecord& r) {
  const size_t n = Size(r.uv());
  return Size(r.right_u()) == n && Size(r.depth()) == n && Size(r.angle()) == n && Size(r.octave()) == n &&
         Size(r.descriptors()) == n && Size(r.points()) == n;
}

}  // namespace flatslam::records
