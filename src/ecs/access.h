// Declared access to a session's components: each step of a system states what it reads and what
// it writes, and takes that access from the session's AccessGuard for the time it runs. Two steps
// conflict when one writes a component the other reads or writes; the guard never lets
// conflicting steps run at once, and lets steps that only read a component share it. The jobs
// layer checks the same declarations when it builds a graph (jobs/system_graph.h).
// Concurrency: Access is a value; AccessGuard::Acquire from any thread (locks are taken in
// component order, so two leases never wait on each other in a cycle).
#pragma once

#include <array>
#include <cstdint>
#include <initializer_list>
#include <mutex>
#include <shared_mutex>
#include <string>

namespace flatslam {

// What a SLAM session holds, one lock each.
enum class Component : uint8_t {
  kMap,           // keyframes, points, observations, covisibility
  kTracker,       // tracking's state from frame to frame
  kLocalMapping,  // points on probation, culled keyframes, mapping's buffers
  kPlaceIndex,    // the keyframe database
  kLoops,         // loop detection's consistency groups and the loops closed
  kTrajectory,    // every tracked frame's pose record
  kCount
};
[[nodiscard]] const char* ComponentName(Component c);

struct Access {
  uint32_t reads = 0, writes = 0;  // bit per Component

  [[nodiscard]] static constexpr uint32_t Bits(std::initializer_list<Component> components) {
    uint32_t bits = 0;
    for (Component c : components) bits |= 1u << static_cast<uint32_t>(c);
    return bits;
  }
  [[nodiscard]] static constexpr Access Of(std::initializer_list<Component> reads,
                                           std::initializer_list<Component> writes) {
    return Access{Bits(reads), Bits(writes)};
  }
  [[nodiscard]] constexpr uint32_t touches() const { return reads | writes; }
  // One writes what the other reads or writes.
  [[nodiscard]] constexpr bool ConflictsWith(const Access& other) const {
    return (writes & other.touches()) != 0 || (other.writes & touches()) != 0;
  }
  // The components behind a conflict, named ("map, place index"); empty when none.
  [[nodiscard]] std::string ConflictWith(const Access& other) const;
};

// A step of a system with the access it declares and the lane it runs on: steps of one lane run
// one at a time unless the lane is parallel (many instances at once); a guarded step takes its
// access from an AccessGuard while it runs. jobs/system_graph.h checks a run's steps.
struct AccessStep {
  const char* name;
  Access access;
  const char* lane;
  bool parallel = false;
  bool guarded = false;
};

class AccessGuard {
 public:
  // Holds the access until destroyed: writes exclusively, reads shared.
  class Lease {
   public:
    Lease(AccessGuard& guard, const Access& access);
    ~Lease();
    Lease(const Lease&) = delete;
    Lease& operator=(const Lease&) = delete;

   private:
    AccessGuard& guard_;
    Access access_;
  };
  [[nodiscard]] Lease Acquire(const Access& access) { return Lease(*this, access); }

 private:
  std::array<std::shared_mutex, static_cast<size_t>(Component::kCount)> locks_;
};

inline const char* ComponentName(Component c) {
  switch (c) {
    case Component::kMap:
      return "map";
    case Component::kTracker:
      return "tracker";
    case Component::kLocalMapping:
      return "local mapping";
    case Component::kPlaceIndex:
      return "place index";
    case Component::kLoops:
      return "loops";
    case Component::kTrajectory:
      return "trajectory";
    case Component::kCount:
      break;
  }
  return "?";
}

inline std::string Access::ConflictWith(const Access& other) const {
  const uint32_t bits = (writes & other.touches()) | (other.writes & touches());
  std::string out;
  for (uint32_t c = 0; c < static_cast<uint32_t>(Component::kCount); ++c) {
    if (!(bits & (1u << c))) continue;
    if (!out.empty()) out += ", ";
    out += ComponentName(static_cast<Component>(c));
  }
  return out;
}

inline AccessGuard::Lease::Lease(AccessGuard& guard, const Access& access) : guard_(guard), access_(access) {
  for (uint32_t c = 0; c < static_cast<uint32_t>(Component::kCount); ++c) {
    if (access_.writes & (1u << c))
      guard_.locks_[c].lock();
    else if (access_.reads & (1u << c))
      guard_.locks_[c].lock_shared();
  }
}

inline AccessGuard::Lease::~Lease() {
  for (uint32_t c = static_cast<uint32_t>(Component::kCount); c-- > 0;) {
    if (access_.writes & (1u << c))
      guard_.locks_[c].unlock();
    else if (access_.reads & (1u << c))
      guard_.locks_[c].unlock_shared();
  }
}

}  // namespace flatslam
