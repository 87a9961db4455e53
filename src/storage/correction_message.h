// The map server's correction for a live agent (schemas/correction.fbs): the similarity that
// takes the agent's map frame into the frame of the merged map it joined. Decoding verifies the
// buffer and the values before it returns: a malformed message is an error, never a crash.
// Concurrency: pure functions.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include <Eigen/Core>

namespace flatslam {

struct CorrectionMessage {
  uint64_t revision = 0;
  uint32_t agent = 0;
  uint64_t session = 0;
  uint32_t frame_agent = 0;
  uint64_t frame_session = 0;
  // X_merged = scale * rotation * X_local + translation
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  double scale = 1;
  uint32_t keyframes = 0;
  double rms_m = 0;
  uint32_t runs = 0;
};

[[nodiscard]] std::vector<uint8_t> EncodeCorrectionMessage(const CorrectionMessage& message);
// Throws flatslam::Error naming `what` and the first problem: not a correction, a newer format,
// corrupt, a rotation that is not one, a non-positive or non-finite scale or translation.
[[nodiscard]] CorrectionMessage DecodeCorrectionMessage(std::span<const uint8_t> bytes, const std::string& what);

}  // namespace flatslam
