// Options written once. An options struct lists each field a user may set in one X-macro entry,
//   X(type, name, default, requirement, "what it does and why")
// and the struct takes from that one list its fields (FLATSLAM_OPTION_FIELD), the check of
// every requirement by its text (FieldsProblem) and a walk over every field with its name and
// description (VisitFields), which `--set`, `--config` and `--list-options` read
// (config/slam_config.h). Adding an option is adding one entry.
// Concurrency: plain values; VisitFields calls `visit` on the calling thread.
#pragma once

#include <string>

#include "core/requirements.h"

// The field itself, with its default.
#define FLATSLAM_OPTION_FIELD(type, name, value, requirement, description) type name = value;
// Internal to FLATSLAM_OPTION_MEMBERS.
#define FLATSLAM_OPTION_VISIT_(type, name, value, requirement, description) visit(#name, name, description);
#define FLATSLAM_OPTION_REQUIRE_(type, name, value, requirement, description) FLATSLAM_REQUIRE(r, requirement);

// Inside the struct, after the fields: VisitFields(visit) calls visit(name, field&, description)
// for every listed field in order; FieldsProblem() is the text of the first requirement broken
// (empty: every one holds).
#define FLATSLAM_OPTION_MEMBERS(LIST)               \
  template <class Visit>                            \
  void VisitFields(Visit&& visit) {                 \
    LIST(FLATSLAM_OPTION_VISIT_)                    \
  }                                                 \
  [[nodiscard]] std::string FieldsProblem() const { \
    ::flatslam::Requirements r;                     \
    LIST(FLATSLAM_OPTION_REQUIRE_)                  \
    return r.first();                               \
  }
