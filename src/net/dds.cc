#include "net/dds.h"

#include <map>
#include <mutex>

#include <fastdds/dds/domain/DomainParticipant.hpp>
#include <fastdds/dds/domain/DomainParticipantFactory.hpp>
#include <fastdds/dds/publisher/DataWriter.hpp>
#include <fastdds/dds/publisher/DataWriterListener.hpp>
#include <fastdds/dds/publisher/Publisher.hpp>
#include <fastdds/dds/subscriber/DataReader.hpp>
#include <fastdds/dds/subscriber/DataReaderListener.hpp>
#include <fastdds/dds/subscriber/SampleInfo.hpp>
#include <fastdds/dds/subscriber/Subscriber.hpp>
#include <fastdds/dds/topic/TypeSupport.hpp>
#include <fastdds/rtps/transport/UDPv4TransportDescriptor.h>
#include <fastrtps/utils/IPLocator.h>

#include "core/error.h"

namespace flatslam {

namespace dds = eprosima::fastdds::dds;
using eprosima::fastrtps::rtps::IPLocator;
using eprosima::fastrtps::rtps::Locator_t;

namespace {

// Participants per host that unicast discovery reaches (Fast DDS's default is 4; a server, a few
// agents and a viewer on one machine need more).
constexpr uint32_t kParticipantsPerPeer = 32;

// The quality of service of a writer or reader (DataWriterQos and DataReaderQos share these).
template <class Qos>
Qos WithQuality(Qos qos, DdsQuality quality) {
  qos.endpoint().history_memory_policy = eprosima::fastrtps::rtps::DYNAMIC_REUSABLE_MEMORY_MODE;
  if (quality == DdsQuality::kReliable) {
    qos.reliability().kind = dds::RELIABLE_RELIABILITY_QOS;
    // Volatile: a sample leaves the writer's history once every matched reader acknowledged it
    // (at once when none is matched), so a long-running writer's memory stays flat. A reader
    // that joins later gets what is written after it matched; agents send their whole map again
    // when a new reader matches (Writer::matches_ever).
    qos.durability().kind = dds::VOLATILE_DURABILITY_QOS;
    qos.history().kind = dds::KEEP_ALL_HISTORY_QOS;
    qos.resource_limits().max_samples = dds::LENGTH_UNLIMITED;
    qos.resource_limits().max_samples_per_instance = dds::LENGTH_UNLIMITED;
  } else {
    qos.reliability().kind = dds::BEST_EFFORT_RELIABILITY_QOS;
    qos.durability().kind = dds::VOLATILE_DURABILITY_QOS;
    qos.history().kind = dds::KEEP_LAST_HISTORY_QOS;
    qos.history().depth = 1;
  }
  return qos;
}

template <class T>
struct TypeOf;
template <>
struct TypeOf<PoseStamped> {
  using Support = PoseStampedType;
};
template <>
struct TypeOf<Payload> {
  using Support = PayloadType;
};

}  // namespace

std::string AgentPoseTopic(uint32_t agent) {
  return "rt/flatslam/agent_" + std::to_string(agent) + "/pose";
}

struct DdsNode::Impl {
  dds::DomainParticipant* participant = nullptr;
  dds::Publisher* publisher = nullptr;
  dds::Subscriber* subscriber = nullptr;
  std::mutex mutex;  // topics and types
  std::map<std::string, dds::Topic*> topics;
  std::map<std::string, dds::TypeSupport> types;

  template <class T>
  dds::Topic* TopicFor(const std::string& name) {
    const std::lock_guard<std::mutex> lock(mutex);
    using Support = typename TypeOf<T>::Support;
    if (!types.count(Support::kName)) {
      dds::TypeSupport type(new Support());
      FLATSLAM_CHECK(type.register_type(participant) == ReturnCode_t::RETCODE_OK, "DDS: cannot register type ",
                     Support::kName);
      types.emplace(Support::kName, type);
    }
    if (auto it = topics.find(name); it != topics.end()) return it->second;
    dds::Topic* topic = participant->create_topic(name, Support::kName, dds::TOPIC_QOS_DEFAULT);
    FLATSLAM_CHECK(topic != nullptr, "DDS: cannot create topic ", name, " of type ", Support::kName);
    topics.emplace(name, topic);
    return topic;
  }
};

template <class T>
struct DdsNode::Writer<T>::Impl : public dds::DataWriterListener {
  dds::Publisher* publisher = nullptr;
  dds::DataWriter* writer = nullptr;
  std::atomic<int> matched{0}, matched_ever{0};
  void on_publication_matched(dds::DataWriter*, const dds::PublicationMatchedStatus& status) override {
    matched = status.current_count;
    matched_ever = status.total_count;
  }
};

template <class T>
bool DdsNode::Writer<T>::Write(const T& sample) {
  return impl_->writer && impl_->writer->write(const_cast<T*>(&sample));
}
template <class T>
int DdsNode::Writer<T>::matched() const {
  return impl_->matched.load();
}
template <class T>
int DdsNode::Writer<T>::matches_ever() const {
  return impl_->matched_ever.load();
}
template <class T>
bool DdsNode::Writer<T>::WaitForAcknowledgments(double seconds) {
  return impl_->writer &&
         impl_->writer->wait_for_acknowledgments(eprosima::fastrtps::Duration_t(seconds)) == ReturnCode_t::RETCODE_OK;
}
template <class T>
DdsNode::Writer<T>::~Writer() {
  if (impl_ && impl_->writer) impl_->publisher->delete_datawriter(impl_->writer);
}

template <class T>
struct DdsNode::Reader<T>::Impl : public dds::DataReaderListener {
  dds::Subscriber* subscriber = nullptr;
  dds::DataReader* reader = nullptr;
  std::function<void(const T&)> on_sample;
  std::atomic<int> matched{0};
  void on_subscription_matched(dds::DataReader*, const dds::SubscriptionMatchedStatus& status) override {
    matched = status.current_count;
  }
  void on_data_available(dds::DataReader* r) override {
    T sample;
    dds::SampleInfo info;
    while (r->take_next_sample(&sample, &info) == ReturnCode_t::RETCODE_OK)
      if (info.valid_data) on_sample(sample);
  }
};

template <class T>
int DdsNode::Reader<T>::matched() const {
  return impl_->matched.load();
}
template <class T>
DdsNode::Reader<T>::~Reader() {
  if (impl_ && impl_->reader) impl_->subscriber->delete_datareader(impl_->reader);
}

DdsNode::DdsNode(const DdsOptions& options, const std::string& name) : impl_(std::make_unique<Impl>()) {
  dds::DomainParticipantQos qos = dds::PARTICIPANT_QOS_DEFAULT;
  qos.name(name);
  if (!options.peers.empty()) {
    auto udp = std::make_shared<eprosima::fastdds::rtps::UDPv4TransportDescriptor>();
    udp->maxInitialPeersRange = kParticipantsPerPeer;
    qos.transport().user_transports.push_back(udp);
    qos.transport().use_builtin_transports = false;
    for (const std::string& peer : options.peers) {
      Locator_t locator;
      FLATSLAM_CHECK(IPLocator::setIPv4(locator, peer), "DDS: '", peer, "' is not an IPv4 address");
      qos.wire_protocol().builtin.initialPeersList.push_back(locator);
    }
  }
  impl_->participant = dds::DomainParticipantFactory::get_instance()->create_participant(options.domain, qos);
  FLATSLAM_CHECK(impl_->participant != nullptr, "DDS: cannot join domain ", options.domain);
  impl_->publisher = impl_->participant->create_publisher(dds::PUBLISHER_QOS_DEFAULT);
  impl_->subscriber = impl_->participant->create_subscriber(dds::SUBSCRIBER_QOS_DEFAULT);
  FLATSLAM_CHECK(impl_->publisher && impl_->subscriber, "DDS: cannot create a publisher and a subscriber");
}

DdsNode::~DdsNode() {
  if (!impl_->participant) return;
  impl_->participant->delete_contained_entities();
  dds::DomainParticipantFactory::get_instance()->delete_participant(impl_->participant);
}

template <class T>
std::unique_ptr<DdsNode::Writer<T>> DdsNode::MakeWriter(const std::string& topic, DdsQuality quality) {
  auto writer = std::unique_ptr<Writer<T>>(new Writer<T>());
  writer->impl_ = std::make_unique<typename Writer<T>::Impl>();
  writer->impl_->publisher = impl_->publisher;
  writer->impl_->writer = impl_->publisher->create_datawriter(
      impl_->TopicFor<T>(topic), WithQuality(impl_->publisher->get_default_datawriter_qos(), quality),
      writer->impl_.get());
  FLATSLAM_CHECK(writer->impl_->writer != nullptr, "DDS: cannot write topic ", topic);
  return writer;
}

template <class T>
std::unique_ptr<DdsNode::Reader<T>> DdsNode::MakeReader(const std::string& topic, DdsQuality quality,
                                                        std::function<void(const T&)> on_sample) {
  auto reader = std::unique_ptr<Reader<T>>(new Reader<T>());
  reader->impl_ = std::make_unique<typename Reader<T>::Impl>();
  reader->impl_->subscriber = impl_->subscriber;
  reader->impl_->on_sample = std::move(on_sample);
  reader->impl_->reader = impl_->subscriber->create_datareader(
      impl_->TopicFor<T>(topic), WithQuality(impl_->subscriber->get_default_datareader_qos(), quality),
      reader->impl_.get());
  FLATSLAM_CHECK(reader->impl_->reader != nullptr, "DDS: cannot read topic ", topic);
  return reader;
}

std::unique_ptr<DdsNode::Writer<PoseStamped>> DdsNode::PoseWriter(const std::string& topic) {
  return MakeWriter<PoseStamped>(topic, DdsQuality::kBestEffort);
}
std::unique_ptr<DdsNode::Writer<Payload>> DdsNode::PayloadWriter(const std::string& topic) {
  return MakeWriter<Payload>(topic, DdsQuality::kReliable);
}
std::unique_ptr<DdsNode::Reader<PoseStamped>> DdsNode::PoseReader(const std::string& topic,
                                                                  std::function<void(const PoseStamped&)> on_sample) {
  return MakeReader<PoseStamped>(topic, DdsQuality::kBestEffort, std::move(on_sample));
}
std::unique_ptr<DdsNode::Reader<Payload>> DdsNode::PayloadReader(const std::string& topic,
                                                                 std::function<void(const Payload&)> on_sample) {
  return MakeReader<Payload>(topic, DdsQuality::kReliable, std::move(on_sample));
}

template class DdsNode::Writer<PoseStamped>;
template class DdsNode::Writer<Payload>;
template class DdsNode::Reader<PoseStamped>;
template class DdsNode::Reader<Payload>;

}  // namespace flatslam
