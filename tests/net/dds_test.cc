#include "net/dds.h"

#include <unistd.h>

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>
#include <vector>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

// A domain of its own per test process, so that tests running side by side never meet.
DdsOptions TestDomain() {
  DdsOptions options;
  options.domain = 100 + static_cast<uint32_t>(getpid() % 100);
  return options;
}

template <class T>
struct Inbox {
  std::mutex mutex;
  std::condition_variable cv;
  std::vector<T> samples;
  void Push(const T& sample) {
    {
      const std::lock_guard<std::mutex> lock(mutex);
      samples.push_back(sample);
    }
    cv.notify_all();
  }
  bool WaitFor(size_t n, double seconds) {
    std::unique_lock<std::mutex> lock(mutex);
    return cv.wait_for(lock, std::chrono::duration<double>(seconds), [&] { return samples.size() >= n; });
  }
};

template <class Writer>
bool WaitMatched(const Writer& writer, double seconds) {
  const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (writer.matched() == 0 && std::chrono::steady_clock::now() < end)
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  return writer.matched() > 0;
}

// A pose crosses from one participant to another with every field as sent, under the DDS type name
// and topic a ROS 2 node would use.
TEST(Dds, PoseStampedReachesAnotherParticipant) {
  DdsNode a(TestDomain(), "test writer"), b(TestDomain(), "test reader");
  Inbox<PoseStamped> inbox;
  auto reader = b.PoseReader(AgentPoseTopic(4), [&](const PoseStamped& p) { inbox.Push(p); });
  auto writer = a.PoseWriter(AgentPoseTopic(4));
  EXPECT_EQ(AgentPoseTopic(4), "rt/flatslam/agent_4/pose");
  EXPECT_STREQ(PoseStampedType::kName, "geometry_msgs::msg::dds_::PoseStamped_");
  ASSERT_TRUE(WaitMatched(*writer, 20)) << "no discovery on loopback within 20 s";
  PoseStamped sent;
  sent.sec = 1234;
  sent.nanosec = 567890;
  sent.frame_id = "flatslam_agent_4_map";
  sent.position = {1.5, -2.25, 3.125};
  sent.orientation = {0.1, 0.2, 0.3, 0.927};
  // Best effort: repeat until one arrives.
  for (int i = 0; i < 100 && inbox.samples.empty(); ++i) {
    writer->Write(sent);
    inbox.WaitFor(1, 0.05);
  }
  ASSERT_TRUE(inbox.WaitFor(1, 5));
  const PoseStamped& got = inbox.samples.front();
  EXPECT_EQ(got.sec, 1234);
  EXPECT_EQ(got.nanosec, 567890u);
  EXPECT_EQ(got.frame_id, "flatslam_agent_4_map");
  EXPECT_EQ(got.position, sent.position);
  EXPECT_EQ(got.orientation, sent.orientation);
}

// Reliable payloads arrive in order, large ones too. The writer keeps no history for readers that
// join later (its memory stays flat): a late reader gets what is written after it matched, and the
// writer counts the match, which is how an agent knows to send its map again.
TEST(Dds, ReliablePayloadsReachAMatchedReaderInOrderAndALateOneIsCounted) {
  DdsNode a(TestDomain(), "test writer"), b(TestDomain(), "test late reader");
  auto writer = a.PayloadWriter("flatslam/test_payloads");
  auto payload = [](uint64_t i) {
    Payload p;
    p.agent = 2;
    p.sequence = i;
    p.bytes.resize(i == 27 ? 300000 : 100 + i);  // one larger than a UDP datagram: fragmented
    for (size_t k = 0; k < p.bytes.size(); ++k) p.bytes[k] = static_cast<uint8_t>(k * 31 + i);
    return p;
  };
  for (uint64_t i = 0; i < 20; ++i) ASSERT_TRUE(writer->Write(payload(i)));  // nobody listens yet
  EXPECT_EQ(writer->matches_ever(), 0);
  Inbox<Payload> inbox;
  auto reader = b.PayloadReader("flatslam/test_payloads", [&](const Payload& p) { inbox.Push(p); });
  ASSERT_TRUE(WaitMatched(*writer, 30));
  EXPECT_EQ(writer->matches_ever(), 1);
  std::vector<Payload> sent;
  for (uint64_t i = 20; i < 40; ++i) {
    sent.push_back(payload(i));
    ASSERT_TRUE(writer->Write(sent.back()));
  }
  ASSERT_TRUE(inbox.WaitFor(sent.size(), 30)) << inbox.samples.size() << " of " << sent.size() << " arrived";
  EXPECT_TRUE(writer->WaitForAcknowledgments(10));
  const std::lock_guard<std::mutex> lock(inbox.mutex);
  ASSERT_EQ(inbox.samples.size(), sent.size()) << "payloads written before the reader matched arrived";
  for (size_t i = 0; i < sent.size(); ++i) {
    EXPECT_EQ(inbox.samples[i].sequence, sent[i].sequence);
    EXPECT_EQ(inbox.samples[i].agent, 2u);
    EXPECT_EQ(inbox.samples[i].bytes, sent[i].bytes) << i;
  }
}

}  // namespace
}  // namespace flatslam
