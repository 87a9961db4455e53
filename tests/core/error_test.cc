#include "core/error.h"

#include <string>

#include <gtest/gtest.h>

namespace flatslam {
namespace {

int CheckPositive(int value) {
  FLATSLAM_CHECK(value > 0, "value must be positive, got ", value);
  return value;
}

// A failed check carries its message for the user, and the source line and condition for a bug
// report; errors raised directly carry no place.
TEST(Error, FailedCheckNamesItsMessageLineAndCondition) {
  try {
    (void)CheckPositive(-3);
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_EQ(std::string(e.what()), "value must be positive, got -3");
    const std::string where = e.where();
    // The file as the compiler saw it, relative to the source tree (a compiler cache may prefix
    // it with "../"), then the line.
    EXPECT_NE(where.find("tests/core/error_test.cc:"), std::string::npos) << where;
    EXPECT_NE(where.rfind('/', 0), 0u) << where;  // never the checkout's absolute path
    EXPECT_NE(where.find(": value > 0"), std::string::npos) << where;
  }
  EXPECT_EQ(CheckPositive(2), 2);
  try {
    Fail("plain ", 1);
  } catch (const Error& e) {
    EXPECT_EQ(std::string(e.what()), "plain 1");
    EXPECT_EQ(std::string(e.where()), "");
  }
}

}  // namespace
}  // namespace flatslam
