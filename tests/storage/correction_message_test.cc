#include "storage/correction_message.h"

#include <random>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <gtest/gtest.h>

#include "core/error.h"

namespace flatslam {
namespace {

std::string CorrectionErrorOf(std::span<const uint8_t> bytes) {
  try {
    (void)DecodeCorrectionMessage(bytes, "correction 4 for agent 2");
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

CorrectionMessage Example() {
  CorrectionMessage c;
  c.revision = 9;
  c.agent = 2;
  c.session = 0x1234567890abcdefULL;
  c.frame_agent = 0;
  c.frame_session = 77;
  c.rotation = Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  c.translation = Eigen::Vector3d(1.5, -2, 0.25);
  c.scale = 1.3;
  c.keyframes = 41;
  c.rms_m = 0.02;
  c.runs = 3;
  return c;
}

TEST(CorrectionMessage, RoundTrips) {
  const CorrectionMessage c = Example();
  const CorrectionMessage d = DecodeCorrectionMessage(EncodeCorrectionMessage(c), "test");
  EXPECT_EQ(d.revision, 9u);
  EXPECT_EQ(d.agent, 2u);
  EXPECT_EQ(d.session, c.session);
  EXPECT_EQ(d.frame_agent, 0u);
  EXPECT_EQ(d.frame_session, 77u);
  EXPECT_EQ(d.rotation, c.rotation);
  EXPECT_EQ(d.translation, c.translation);
  EXPECT_EQ(d.scale, 1.3);
  EXPECT_EQ(d.keyframes, 41u);
  EXPECT_EQ(d.rms_m, 0.02);
  EXPECT_EQ(d.runs, 3u);
}

// A correction moves every pose an agent publishes: anything that is not a similarity is refused,
// naming the message, and so is every corrupt buffer; never a crash.
TEST(CorrectionMessage, MalformedCorrectionsAreRefusedWithTheirName) {
  const std::vector<uint8_t> bytes = EncodeCorrectionMessage(Example());
  EXPECT_NE(CorrectionErrorOf({}).find("correction 4 for agent 2: not a correction message"), std::string::npos);
  CorrectionMessage bad = Example();
  bad.rotation(0, 0) += 0.1;
  EXPECT_NE(CorrectionErrorOf(EncodeCorrectionMessage(bad)).find("not a rotation"), std::string::npos);
  bad = Example();
  bad.rotation = -bad.rotation;  // a reflection
  EXPECT_NE(CorrectionErrorOf(EncodeCorrectionMessage(bad)).find("not a rotation"), std::string::npos);
  bad = Example();
  bad.scale = 0;
  EXPECT_NE(CorrectionErrorOf(EncodeCorrectionMessage(bad)).find("scale 0"), std::string::npos);
  bad = Example();
  bad.translation.y() = std::nan("");
  EXPECT_NE(CorrectionErrorOf(EncodeCorrectionMessage(bad)).find("translation is not finite"), std::string::npos);
  for (size_t n = 0; n < bytes.size(); n += 7) {
    EXPECT_NE(CorrectionErrorOf(std::span(bytes).first(n)).find("correction 4 for agent 2"), std::string::npos) << n;
  }
  std::mt19937_64 rng(3);
  size_t refused = 0;
  for (int trial = 0; trial < 300; ++trial) {
    std::vector<uint8_t> flipped = bytes;
    flipped[rng() % flipped.size()] ^= static_cast<uint8_t>(1 + rng() % 255);
    const std::string error = CorrectionErrorOf(flipped);
    if (!error.empty()) {
      ++refused;
      EXPECT_NE(error.find("correction 4 for agent 2"), std::string::npos) << error;
    }
  }
  EXPECT_GT(refused, 0u);
}

}  // namespace
}  // namespace flatslam
