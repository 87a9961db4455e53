// Checks the steps of a run before it starts: every pair of steps that may run at the same time
// (on different lanes, or twice on a parallel lane) must not conflict (one writing a component
// the other touches), unless both take their access from the same guard at run time
// (ecs/access.h), which then runs them one after the other. A conflict is refused with an error
// naming both steps and the components, so that a step added without its access taken never
// races with another.
// Concurrency: built and checked on one thread before the run.
#pragma once

#include <vector>

#include "ecs/access.h"

namespace flatslam {

class SystemGraph {
 public:
  // Adds a step; throws flatslam::Error when it may run beside a step it conflicts with without
  // both being guarded (a parallel step that writes a component conflicts with itself).
  void Add(const AccessStep& step);
  [[nodiscard]] const std::vector<AccessStep>& steps() const { return steps_; }

 private:
  std::vector<AccessStep> steps_;
};

}  // namespace flatslam
