// flatslam on DDS (eProsima Fast DDS): one participant per process, typed writers and readers
// with the two qualities of service the agents use.
// - Reliable: keyframes and corrections. Every sample is delivered to the readers matched when
//   it is written, in order; the writer keeps it until they all acknowledged it (volatile, keep
//   all), so its memory stays flat. A server that starts late gets an agent's whole map because
//   the agent sends it again when a new reader matches (Writer::matches_ever).
// - BestEffort: poses. The newest sample only; a lost one is replaced by the next.
// Discovery: with `peers` set (the default, 127.0.0.1), participants find each other by unicast
// to those hosts, which works where multicast does not (a container's loopback); an empty list
// uses DDS's default multicast discovery.
// Concurrency: a DdsNode and its writers may be used from any thread; a reader's callback runs
// on a Fast DDS listener thread, one sample at a time per reader. Writers and readers are
// destroyed before the node that made them.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "net/dds_types.h"

namespace flatslam {

struct DdsOptions {
  uint32_t domain = 0;
  std::vector<std::string> peers = {"127.0.0.1"};  // IPv4 addresses for unicast discovery
};

enum class DdsQuality { kReliable, kBestEffort };

// The topics: ROS 2 maps a topic /flatslam/agent_N/pose to the DDS topic rt/flatslam/agent_N/pose.
[[nodiscard]] std::string AgentPoseTopic(uint32_t agent);
inline constexpr const char* kKeyFrameTopic = "flatslam/keyframes";
inline constexpr const char* kCorrectionTopic = "flatslam/corrections";

class DdsNode {
 public:
  // Throws flatslam::Error when the participant cannot be created (names the domain).
  DdsNode(const DdsOptions& options, const std::string& name);
  ~DdsNode();
  DdsNode(const DdsNode&) = delete;
  DdsNode& operator=(const DdsNode&) = delete;

  template <class T>
  class Writer {
   public:
    // False when the sample could not be written (serialization failed, or the writer is gone).
    bool Write(const T& sample);
    // Readers currently matched, and every match since the writer was created (a reader that
    // joined later, or came back, counts again).
    [[nodiscard]] int matched() const;
    [[nodiscard]] int matches_ever() const;
    // Waits until every matched reader acknowledged every sample written (reliable writers), at
    // most `seconds`; false on timeout.
    bool WaitForAcknowledgments(double seconds);
    ~Writer();

   private:
    friend class DdsNode;
    struct Impl;
    std::unique_ptr<Impl> impl_;
  };

  template <class T>
  class Reader {
   public:
    [[nodiscard]] int matched() const;
    ~Reader();

   private:
    friend class DdsNode;
    struct Impl;
    std::unique_ptr<Impl> impl_;
  };

  // A writer or reader of `topic`; throws flatslam::Error naming the topic when DDS refuses it.
  [[nodiscard]] std::unique_ptr<Writer<PoseStamped>> PoseWriter(const std::string& topic);
  [[nodiscard]] std::unique_ptr<Writer<Payload>> PayloadWriter(const std::string& topic);
  [[nodiscard]] std::unique_ptr<Reader<PoseStamped>> PoseReader(const std::string& topic,
                                                                std::function<void(const PoseStamped&)> on_sample);
  [[nodiscard]] std::unique_ptr<Reader<Payload>> PayloadReader(const std::string& topic,
                                                               std::function<void(const Payload&)> on_sample);

 private:
  template <class T>
  std::unique_ptr<Writer<T>> MakeWriter(const std::string& topic, DdsQuality quality);
  template <class T>
  std::unique_ptr<Reader<T>> MakeReader(const std::string& topic, DdsQuality quality,
                                        std::function<void(const T&)> on_sample);

  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace flatslam
