// Test helper: a call must throw flatslam::Error whose message names every given part.
#pragma once

#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/error.h"

namespace flatslam::testing {

template <class Fn>
void ExpectErrorMentions(Fn&& fn, const std::vector<std::string>& parts) {
  try {
    fn();
    FAIL() << "expected flatslam::Error";
  } catch (const Error& e) {
    for (const auto& part : parts) EXPECT_NE(std::string(e.what()).find(part), std::string::npos) << e.what();
  }
}

}  // namespace flatslam::testing
