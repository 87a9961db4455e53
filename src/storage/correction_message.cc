#include "storage/correction_message.h"

#include <cmath>

#include <Eigen/LU>

#include "core/error.h"
#include "flatslam/schemas/correction_generated.h"
#include "storage/schema_records.h"

namespace flatslam {
namespace {

constexpr uint32_t kFormatVersion = 1;

}  // namespace

std::vector<uint8_t> EncodeCorrectionMessage(const CorrectionMessage& m) {
  flatbuffers::FlatBufferBuilder builder(512);
  std::vector<double> rotation(9), translation(3);
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) rotation[3 * r + c] = m.rotation(r, c);
    translation[r] = m.translation[r];
  }
  const auto rotation_vector = builder.CreateVector(rotation);
  const auto translation_vector = builder.CreateVector(translation);
  agent::FinishCorrectionMessageBuffer(
      builder, agent::CreateCorrectionMessage(builder, kFormatVersion, m.revision, m.agent, m.session, m.frame_agent,
                                              m.frame_session, rotation_vector, translation_vector, m.scale,
                                              m.keyframes, m.rms_m, m.runs));
  return {builder.GetBufferPointer(), builder.GetBufferPointer() + builder.GetSize()};
}

CorrectionMessage DecodeCorrectionMessage(std::span<const uint8_t> bytes, const std::string& what) {
  const agent::CorrectionMessage& root = records::VerifiedMessage<agent::CorrectionMessage>(
      bytes, agent::CorrectionMessageIdentifier(), kFormatVersion, what, "correction message");
  FLATSLAM_CHECK(
      root.rotation() && root.rotation()->size() == 9 && root.translation() && root.translation()->size() == 3, what,
      ": a rotation needs 9 values and a translation 3");
  CorrectionMessage m;
  m.revision = root.revision();
  m.agent = root.agent();
  m.session = root.session();
  m.frame_agent = root.frame_agent();
  m.frame_session = root.frame_session();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) m.rotation(r, c) = root.rotation()->Get(3 * r + c);
    m.translation[r] = root.translation()->Get(r);
  }
  m.scale = root.scale();
  m.keyframes = root.keyframes();
  m.rms_m = root.rms_m();
  m.runs = root.runs();
  const Eigen::Matrix3d& R = m.rotation;
  FLATSLAM_CHECK(
      R.allFinite() && (R * R.transpose() - Eigen::Matrix3d::Identity()).norm() < 1e-6 && R.determinant() > 0, what,
      ": its rotation is not a rotation");
  FLATSLAM_CHECK(m.translation.allFinite(), what, ": its translation is not finite");
  FLATSLAM_CHECK(std::isfinite(m.scale) && m.scale > 0, what, ": scale ", m.scale, " (must be positive)");
  FLATSLAM_CHECK(std::isfinite(m.rms_m) && m.rms_m >= 0, what, ": residual ", m.rms_m);
  return m;
}

}  // namespace flatslam
