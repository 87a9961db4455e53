// Checks the steps of a run before it starts: every pair of steps that may run at the same time
// (on different lanes, or twice on a parallel lane) must not conflict (one writing a component
// the other touches), unless both take their access from the same guard at run time
// (ecs/access.h), which then runs them one after the other. A conflict is refused with an error
// naming both steps and the components, so that a step added without its access taken never
// races with another.
// Concurrency: built and checked on one thread before the run.
#pragma once

#include <span>
#include <string>
#include <vector>

#include "ecs/access.h"

namespace flatslam {

class SystemGraph {
 public:
  // Adds a step; throws flatslam::Error when it may run beside a step it conflicts with without
  // both being guarded (a parallel step that writes a component conflicts with itself).
  void Add(const AccessStep& step);
  [[nodiscard]] const std::vector<AccessStep>& steps() const { return steps_; }

  // A lane the steps run on: one scheduler stage, running one step at a time unless parallel.
  struct Lane {
    std::string name;
    bool parallel = false;
  };
  // The lanes the steps declared, in the order first declared; throws flatslam::Error when steps
  // of one lane disagree on whether it is parallel.
  [[nodiscard]] std::vector<Lane> Lanes() const;
  // Checks the stages a scheduler built against the declared lanes: every declared lane has a
  // stage of its kind (parallel or one at a time), and no stage runs a lane no step declared.
  // Throws flatslam::Error naming the lane otherwise, so that a step is never declared on a
  // lane that nothing runs, nor run where its declaration does not say.
  void CheckStages(std::span<const Lane> stages) const;

 private:
  std::vector<AccessStep> steps_;
};

}  // namespace flatslam
