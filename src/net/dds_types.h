// The two sample types flatslam puts on DDS, with their CDR encodings (Fast DDS type support):
// - PoseStamped: ROS 2's geometry_msgs/msg/PoseStamped under its DDS name
//   ("geometry_msgs::msg::dds_::PoseStamped_"), so that ROS 2 tools on the same network read an
//   agent's pose without flatslam depending on ROS;
// - Payload: flatslam's own envelope (agent, kind, sequence number) around a flatbuffers message
//   (storage/keyframe_message.h), which the receiver verifies before it reads anything.
// Concurrency: the type supports are stateless; serialize/deserialize run on any thread.
#pragma once

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include <fastdds/dds/topic/TopicDataType.hpp>

namespace flatslam {

// geometry_msgs/msg/PoseStamped: std_msgs/Header (builtin_interfaces/Time stamp, frame_id) and
// geometry_msgs/Pose (position, orientation as x, y, z, w).
struct PoseStamped {
  int32_t sec = 0;
  uint32_t nanosec = 0;
  std::string frame_id;
  std::array<double, 3> position{};
  std::array<double, 4> orientation{0, 0, 0, 1};
};

// kKeyFrame: an agent's keyframe, kCulled: keyframes it culled after sending them, kRunEnded: its
// run is over (all storage/keyframe_message.h); kCorrection: the server's correction for an agent
// (storage/correction_message.h), `agent` being the agent it is for.
enum class PayloadKind : uint32_t { kKeyFrame = 1, kCorrection = 2, kCulled = 3, kRunEnded = 4 };

struct Payload {
  uint32_t agent = 0;
  PayloadKind kind = PayloadKind::kKeyFrame;
  uint64_t sequence = 0;  // per agent and kind, from 0
  std::vector<uint8_t> bytes;
};

class PoseStampedType : public eprosima::fastdds::dds::TopicDataType {
 public:
  static constexpr const char* kName = "geometry_msgs::msg::dds_::PoseStamped_";
  PoseStampedType();
  bool serialize(void* data, eprosima::fastrtps::rtps::SerializedPayload_t* payload) override;
  bool deserialize(eprosima::fastrtps::rtps::SerializedPayload_t* payload, void* data) override;
  std::function<uint32_t()> getSerializedSizeProvider(void* data) override;
  void* createData() override { return new PoseStamped(); }
  void deleteData(void* data) override { delete static_cast<PoseStamped*>(data); }
  bool getKey(void*, eprosima::fastrtps::rtps::InstanceHandle_t*, bool) override { return false; }
};

class PayloadType : public eprosima::fastdds::dds::TopicDataType {
 public:
  static constexpr const char* kName = "flatslam::msg::Payload";
  PayloadType();
  bool serialize(void* data, eprosima::fastrtps::rtps::SerializedPayload_t* payload) override;
  bool deserialize(eprosima::fastrtps::rtps::SerializedPayload_t* payload, void* data) override;
  std::function<uint32_t()> getSerializedSizeProvider(void* data) override;
  void* createData() override { return new Payload(); }
  void deleteData(void* data) override { delete static_cast<Payload*>(data); }
  bool getKey(void*, eprosima::fastrtps::rtps::InstanceHandle_t*, bool) override { return false; }
};

}  // namespace flatslam
