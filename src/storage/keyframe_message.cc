#include "storage/keyframe_message.h"

#include <cmath>
#include <optional>
#include <unordered_map>

#include "core/error.h"
#include "flatslam/schemas/agent_generated.h"
#include "flatslam/schemas/culled_generated.h"
#include "flatslam/schemas/run_ended_generated.h"
#include "storage/schema_records.h"

namespace flatslam {
namespace {

constexpr uint32_t kFormatVersion = 1;
// Keyframe messages: 2 sends points as their position in the keyframe's camera frame (1: map
// snapshots' point records, no longer read).
constexpr uint32_t kKeyFrameFormatVersion = 2;

bool Finite(const Eigen::Vector3d& v) {
  return std::isfinite(v.x()) && std::isfinite(v.y()) && std::isfinite(v.z());
}

}  // namespace

std::vector<uint8_t> EncodeKeyFrameMessage(const Map& map, KeyFrameHandle keyframe, uint32_t agent, uint64_t session,
                                           const AgentCamera& camera, const Eigen::Isometry3d& T_out_map,
                                           double scale) {
  const KeyFrame& kf = map.keyframe(keyframe);
  // Points go in the keyframe's camera frame, which a rigid move of the map's frame leaves alone
  // (a scaled one scales them): only the pose is written in the frame asked for.
  std::optional<KeyFrame> moved_keyframe;
  if (!T_out_map.isApprox(Eigen::Isometry3d::Identity(), 0.0) || scale != 1.0) {
    moved_keyframe = kf;  // keypoint columns shared, not copied
    moved_keyframe->T_cam_world = MovedCameraPose(kf.T_cam_world, T_out_map, scale);
  }
  // The keyframe's live points, in the order its keypoints first see them.
  std::unordered_map<PointHandle, uint32_t> index;
  std::vector<uint64_t> ids;
  std::vector<agent::Vec3f> positions;
  for (PointHandle p : kf.points) {
    const MapPoint* point = map.points().try_get(p);
    if (!point || index.count(p)) continue;
    index.emplace(p, static_cast<uint32_t>(ids.size()));
    ids.push_back(p.packed());
    const Eigen::Vector3f X = (scale * (kf.T_cam_world * point->position)).cast<float>();
    positions.emplace_back(X.x(), X.y(), X.z());
  }
  flatbuffers::FlatBufferBuilder builder(kf.size() * 80 + positions.size() * 24 + 1024);
  auto point_index = [&](PointHandle p) {
    const auto it = index.find(p);
    return it == index.end() ? records::kNone : it->second;
  };
  const auto record = records::BuildKeyFrameRecord(
      builder, moved_keyframe ? *moved_keyframe : kf, point_index, [](KeyFrameHandle) { return records::kNone; },
      /*graph=*/false);
  const auto id_vector = builder.CreateVector(ids);
  const auto position_vector = builder.CreateVectorOfStructs(positions);
  const auto calibration = records::BuildCalibration(builder, camera.calibration);
  const auto pyramid = schema::CreateScalePyramid(builder, camera.scales.scale_factor, camera.scales.levels);
  agent::KeyFrameMessageBuilder message(builder);
  message.add_format_version(kKeyFrameFormatVersion);
  message.add_agent(agent);
  message.add_session(session);
  message.add_calibration(calibration);
  message.add_scales(pyramid);
  message.add_rgbd_virtual_baseline_m(camera.rgbd_virtual_baseline_m);
  message.add_keyframe(record);
  message.add_point_ids(id_vector);
  message.add_point_positions(position_vector);
  agent::FinishKeyFrameMessageBuffer(builder, message.Finish());
  return {builder.GetBufferPointer(), builder.GetBufferPointer() + builder.GetSize()};
}

KeyFrameMessage DecodeKeyFrameMessage(std::span<const uint8_t> bytes, const std::string& what) {
  const agent::KeyFrameMessage& root = records::VerifiedMessage<agent::KeyFrameMessage>(
      bytes, agent::KeyFrameMessageIdentifier(), kKeyFrameFormatVersion, what, "keyframe message",
      /*min_version=*/kKeyFrameFormatVersion);
  FLATSLAM_CHECK(root.keyframe() != nullptr, what, ": no keyframe");
  const schema::KeyFrameRecord& r = *root.keyframe();
  FLATSLAM_CHECK(records::KeyFrameColumnsAgree(r), what, ": keypoint columns differ in size");
  const size_t np = records::Size(root.point_positions());
  FLATSLAM_CHECK(records::Size(root.point_ids()) == np, what, ": ", records::Size(root.point_ids()), " point ids for ",
                 np, " points");

  FLATSLAM_CHECK(root.calibration() && root.scales(), what, ": no calibration");
  KeyFrameMessage out;
  out.agent = root.agent();
  out.session = root.session();
  AgentCamera& camera = out.camera;
  camera.calibration = records::CalibrationFromRecord(*root.calibration());
  camera.scales = MapScales{root.scales()->scale_factor(), root.scales()->levels()};
  camera.rgbd_virtual_baseline_m = root.rgbd_virtual_baseline_m();
  FLATSLAM_CHECK(camera.calibration.camera.fx > 0 && camera.calibration.camera.width > 0 && camera.scales.levels >= 1 &&
                     camera.scales.levels <= 32 && camera.scales.scale_factor >= 1,
                 what, ": calibration out of range");
  out.keyframe = records::KeyFrameFromRecord(r);
  FLATSLAM_CHECK(out.keyframe.T_cam_world.matrix().allFinite(), what, ": the keyframe's pose is not finite");
  const auto point_index = records::Span(r.points());
  out.keypoint_point.assign(point_index.begin(), point_index.end());
  for (size_t k = 0; k < out.keypoint_point.size(); ++k) {
    const uint32_t i = out.keypoint_point[k];
    FLATSLAM_CHECK(i == KeyFrameMessage::kNoPoint || i < np, what, ": keypoint ", k, " names point ", i, " of ", np);
  }
  const auto ids = records::Span(root.point_ids());
  out.point_ids.assign(ids.begin(), ids.end());
  out.positions.reserve(np);
  const Eigen::Isometry3d T_world_cam = out.keyframe.T_cam_world.inverse();
  for (const agent::Vec3f& X : records::Span(root.point_positions())) {
    const Eigen::Vector3d X_cam(X.x(), X.y(), X.z());
    FLATSLAM_CHECK(Finite(X_cam), what, ": point ", out.positions.size(), " is not finite");
    out.positions.push_back(T_world_cam * X_cam);
  }
  return out;
}

std::vector<uint8_t> EncodeKeyFramesCulled(const KeyFramesCulled& message) {
  flatbuffers::FlatBufferBuilder builder(64 + 8 * message.keyframes.size());
  const auto ids = builder.CreateVector(message.keyframes);
  agent::FinishKeyFramesCulledBuffer(
      builder, agent::CreateKeyFramesCulled(builder, kFormatVersion, message.agent, message.session, ids));
  return {builder.GetBufferPointer(), builder.GetBufferPointer() + builder.GetSize()};
}

KeyFramesCulled DecodeKeyFramesCulled(std::span<const uint8_t> bytes, const std::string& what) {
  const agent::KeyFramesCulled& root = records::VerifiedMessage<agent::KeyFramesCulled>(
      bytes, agent::KeyFramesCulledIdentifier(), kFormatVersion, what, "culled-keyframes message");
  KeyFramesCulled out;
  out.agent = root.agent();
  out.session = root.session();
  const auto ids = records::Span(root.keyframes());
  out.keyframes.assign(ids.begin(), ids.end());
  return out;
}

std::vector<uint8_t> EncodeRunEnded(const RunEnded& message) {
  flatbuffers::FlatBufferBuilder builder(64);
  agent::FinishRunEndedBuffer(
      builder, agent::CreateRunEnded(builder, kFormatVersion, message.agent, message.session, message.keyframes,
                                     message.frames, message.stopped, message.resumed_by));
  return {builder.GetBufferPointer(), builder.GetBufferPointer() + builder.GetSize()};
}

RunEnded DecodeRunEnded(std::span<const uint8_t> bytes, const std::string& what) {
  const agent::RunEnded& root = records::VerifiedMessage<agent::RunEnded>(bytes, agent::RunEndedIdentifier(),
                                                                          kFormatVersion, what, "run-ended message");
  RunEnded out;
  out.agent = root.agent();
  out.session = root.session();
  out.keyframes = root.keyframes();
  out.frames = root.frames();
  out.stopped = root.stopped();
  out.resumed_by = root.resumed_by();
  return out;
}

}  // namespace flatslam
