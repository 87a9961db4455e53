#include "jobs/system_graph.h"

#include <string_view>

#include "core/error.h"

namespace flatslam {
namespace {

// A step and another may overlap in time: different lanes, or one parallel lane.
bool MayOverlap(const AccessStep& a, const AccessStep& b) {
  return std::string_view(a.lane) != b.lane || (a.parallel && b.parallel);
}

void Refuse(const AccessStep& a, const AccessStep& b) {
  Fail("steps '", a.name, "' (lane ", a.lane, ") and '", b.name, "' (lane ", b.lane,
       ") may run at the same time and conflict on ", a.access.ConflictWith(b.access),
       "; declare the access and take it from the guard, or put them on one lane");
}

}  // namespace

void SystemGraph::Add(const AccessStep& step) {
  // A parallel step meets itself.
  if (step.parallel && !step.guarded && step.access.ConflictsWith(step.access)) Refuse(step, step);
  for (const AccessStep& other : steps_) {
    if (!MayOverlap(step, other) || !step.access.ConflictsWith(other.access)) continue;
    if (step.guarded && other.guarded) continue;  // the guard runs them one after the other
    Refuse(step, other);
  }
  steps_.push_back(step);
}

}  // namespace flatslam
