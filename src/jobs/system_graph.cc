#include "jobs/system_graph.h"

#include <algorithm>
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

std::vector<SystemGraph::Lane> SystemGraph::Lanes() const {
  std::vector<Lane> lanes;
  for (const AccessStep& step : steps_) {
    auto it = std::find_if(lanes.begin(), lanes.end(), [&](const Lane& l) { return l.name == step.lane; });
    if (it == lanes.end()) {
      lanes.push_back({step.lane, step.parallel});
      continue;
    }
    FLATSLAM_CHECK(it->parallel == step.parallel, "step '", step.name, "' declares lane ", step.lane,
                   step.parallel ? " parallel" : " one at a time", ", other steps of that lane declare it ",
                   it->parallel ? "parallel" : "one at a time");
  }
  return lanes;
}

void SystemGraph::CheckStages(std::span<const Lane> stages) const {
  const std::vector<Lane> lanes = Lanes();
  for (const Lane& lane : lanes) {
    auto it = std::find_if(stages.begin(), stages.end(), [&](const Lane& s) { return s.name == lane.name; });
    FLATSLAM_CHECK(it != stages.end(), "lane ", lane.name, " is declared by a step but no stage runs it");
    FLATSLAM_CHECK(it->parallel == lane.parallel, "lane ", lane.name, " is declared ",
                   lane.parallel ? "parallel" : "one at a time", " but its stage runs ",
                   it->parallel ? "in parallel" : "one item at a time");
  }
  for (const Lane& stage : stages)
    FLATSLAM_CHECK(std::any_of(lanes.begin(), lanes.end(), [&](const Lane& l) { return l.name == stage.name; }),
                   "a stage runs lane ", stage.name, ", which no step declares");
}

}  // namespace flatslam
