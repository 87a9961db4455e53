#include "jobs/system_graph.h"

#include <string>

#include <gtest/gtest.h>

#include "core/error.h"
#include "slam/session.h"

namespace flatslam {
namespace {

using C = Component;

std::string Refusal(SystemGraph& graph, const AccessStep& step) {
  try {
    graph.Add(step);
  } catch (const Error& e) {
    return e.what();
  }
  return "";
}

TEST(SystemGraph, RefusesTwoWritersOfTheMapThatMayRunAtOnce) {
  SystemGraph graph;
  graph.Add({"mapping", Access::Of({}, {C::kMap}), "mapping"});
  const std::string error = Refusal(graph, {"merge", Access::Of({}, {C::kMap, C::kPlaceIndex}), "merge"});
  EXPECT_NE(error.find("'merge'"), std::string::npos) << error;
  EXPECT_NE(error.find("'mapping'"), std::string::npos) << error;
  EXPECT_NE(error.find("conflict on map"), std::string::npos) << error;
  // A reader beside a writer conflicts as well; readers beside readers do not.
  EXPECT_FALSE(Refusal(graph, {"viewer", Access::Of({C::kMap}, {}), "viewer"}).empty());
  EXPECT_TRUE(Refusal(graph, {"index", Access::Of({}, {C::kPlaceIndex}), "place"}).empty());
  EXPECT_TRUE(Refusal(graph, {"stats", Access::Of({C::kTrajectory}, {}), "stats"}).empty());
}

TEST(SystemGraph, AcceptsConflictsTheGuardOrALaneSerializes) {
  SystemGraph graph;
  graph.Add({"track", Access::Of({}, {C::kMap}), "track", false, true});
  EXPECT_TRUE(Refusal(graph, {"cull", Access::Of({}, {C::kMap}), "mapping", false, true}).empty());
  // One lane runs its steps one after the other: no guard needed between them.
  SystemGraph lane;
  lane.Add({"prepare", Access::Of({}, {C::kMap}), "mapping"});
  EXPECT_TRUE(Refusal(lane, {"fuse", Access::Of({}, {C::kMap}), "mapping"}).empty());
}

TEST(SystemGraph, AParallelStepThatWritesMeetsItself) {
  SystemGraph graph;
  EXPECT_NE(Refusal(graph, {"extract", Access::Of({}, {C::kMap}), "extract", true}).find("'extract'"),
            std::string::npos);
  EXPECT_TRUE(Refusal(graph, {"extract", Access::Of({C::kMap}, {}), "extract", true}).empty());
}

TEST(SystemGraph, TheSessionsStepsPassAndAnUnguardedTrackIsRefused) {
  SystemGraph graph;
  for (const AccessStep& s : SlamSession::Steps()) EXPECT_NO_THROW(graph.Add(s)) << s.name;
  SystemGraph broken;
  std::string error;
  for (AccessStep s : SlamSession::Steps()) {
    s.guarded = s.guarded && std::string(s.name) != "track";
    error += Refusal(broken, s);
  }
  EXPECT_NE(error.find("'track'"), std::string::npos) << error;
}

}  // namespace
}  // namespace flatslam
