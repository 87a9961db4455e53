#include "net/dds_types.h"

#include <fastcdr/Cdr.h>
#include <fastcdr/FastBuffer.h>
#include <fastcdr/exceptions/Exception.h>

namespace flatslam {
namespace {

using eprosima::fastcdr::Cdr;
using eprosima::fastcdr::FastBuffer;
using eprosima::fastrtps::rtps::SerializedPayload_t;

// Writes `write(cdr)` after the encapsulation header; false when the payload is too small.
template <class Write>
bool Serialize(SerializedPayload_t* payload, Write&& write) {
  FastBuffer buffer(reinterpret_cast<char*>(payload->data), payload->max_size);
  Cdr cdr(buffer, Cdr::DEFAULT_ENDIAN, Cdr::DDS_CDR);
  payload->encapsulation = cdr.endianness() == Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
  try {
    cdr.serialize_encapsulation();
    write(cdr);
  } catch (const eprosima::fastcdr::exception::Exception&) {
    return false;
  }
  payload->length = static_cast<uint32_t>(cdr.getSerializedDataLength());
  return true;
}

// Reads with `read(cdr)`; false when the sample is malformed (too short, bad lengths).
template <class Read>
bool Deserialize(SerializedPayload_t* payload, Read&& read) {
  FastBuffer buffer(reinterpret_cast<char*>(payload->data), payload->length);
  Cdr cdr(buffer, Cdr::DEFAULT_ENDIAN, Cdr::DDS_CDR);
  try {
    cdr.read_encapsulation();
    payload->encapsulation = cdr.endianness() == Cdr::BIG_ENDIANNESS ? CDR_BE : CDR_LE;
    read(cdr);
  } catch (const eprosima::fastcdr::exception::Exception&) {
    return false;
  } catch (const std::bad_alloc&) {
    return false;  // a sequence length larger than memory
  }
  return true;
}

// Encapsulation (4), then the worst-case alignment padding of each field (at most 7 bytes each).
constexpr uint32_t kSlack = 4 + 8 * 8;

}  // namespace

PoseStampedType::PoseStampedType() {
  setName(kName);
  m_typeSize = kSlack + 4 + 4 + 4 + 256 + 7 * 8;
  m_isGetKeyDefined = false;
}

bool PoseStampedType::serialize(void* data, SerializedPayload_t* payload) {
  const PoseStamped& p = *static_cast<const PoseStamped*>(data);
  return Serialize(payload, [&](Cdr& cdr) {
    cdr << p.sec << p.nanosec << p.frame_id;
    for (double v : p.position) cdr << v;
    for (double v : p.orientation) cdr << v;
  });
}

bool PoseStampedType::deserialize(SerializedPayload_t* payload, void* data) {
  PoseStamped& p = *static_cast<PoseStamped*>(data);
  return Deserialize(payload, [&](Cdr& cdr) {
    cdr >> p.sec >> p.nanosec >> p.frame_id;
    for (double& v : p.position) cdr >> v;
    for (double& v : p.orientation) cdr >> v;
  });
}

std::function<uint32_t()> PoseStampedType::getSerializedSizeProvider(void* data) {
  const size_t frame_id = static_cast<const PoseStamped*>(data)->frame_id.size();
  return [frame_id] { return static_cast<uint32_t>(kSlack + 4 + 4 + 4 + frame_id + 1 + 7 * 8); };
}

PayloadType::PayloadType() {
  setName(kName);
  m_typeSize = kSlack + 4 + 4 + 8 + 4 + 64 * 1024;  // grows per sample (getSerializedSizeProvider)
  m_isGetKeyDefined = false;
}

bool PayloadType::serialize(void* data, SerializedPayload_t* payload) {
  const Payload& p = *static_cast<const Payload*>(data);
  return Serialize(payload,
                   [&](Cdr& cdr) { cdr << p.agent << static_cast<uint32_t>(p.kind) << p.sequence << p.bytes; });
}

bool PayloadType::deserialize(SerializedPayload_t* payload, void* data) {
  Payload& p = *static_cast<Payload*>(data);
  return Deserialize(payload, [&](Cdr& cdr) {
    uint32_t kind = 0;
    cdr >> p.agent >> kind >> p.sequence >> p.bytes;
    p.kind = static_cast<PayloadKind>(kind);
  });
}

std::function<uint32_t()> PayloadType::getSerializedSizeProvider(void* data) {
  const size_t bytes = static_cast<const Payload*>(data)->bytes.size();
  return [bytes] { return static_cast<uint32_t>(kSlack + 4 + 4 + 8 + 4 + bytes); };
}

}  // namespace flatslam
