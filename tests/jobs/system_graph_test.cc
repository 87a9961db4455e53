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

// The stages a scheduler builds must be the lanes the steps declare, of the same kind.
TEST(SystemGraph, StagesMustRunTheDeclaredLanes) {
  SystemGraph graph;
  graph.Add({"extract", Access{}, "extract", true});
  graph.Add({"track", Access::Of({}, {C::kMap}), "track", false, true});
  graph.Add({"cull", Access::Of({}, {C::kMap}), "mapping", false, true});
  const std::vector<SystemGraph::Lane> lanes = graph.Lanes();
  ASSERT_EQ(lanes.size(), 3u);
  EXPECT_EQ(lanes[0].name, "extract");
  EXPECT_TRUE(lanes[0].parallel);
  EXPECT_FALSE(lanes[2].parallel);
  const SystemGraph::Lane all[] = {{"extract", true}, {"track", false}, {"mapping", false}};
  EXPECT_NO_THROW(graph.CheckStages(all));
  auto error = [&](std::span<const SystemGraph::Lane> stages) {
    try {
      graph.CheckStages(stages);
    } catch (const Error& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  const SystemGraph::Lane no_mapping[] = {{"extract", true}, {"track", false}};
  EXPECT_NE(error(no_mapping).find("lane mapping is declared by a step but no stage runs it"), std::string::npos);
  const SystemGraph::Lane serial_extract[] = {{"extract", false}, {"track", false}, {"mapping", false}};
  EXPECT_NE(error(serial_extract).find("lane extract is declared parallel"), std::string::npos);
  const SystemGraph::Lane extra[] = {{"extract", true}, {"track", false}, {"mapping", false}, {"viewer", false}};
  EXPECT_NE(error(extra).find("a stage runs lane viewer, which no step declares"), std::string::npos);
  // Steps of one lane agree on its kind.
  graph.Add({"read", Access{}, "track", true});
  EXPECT_THROW((void)graph.Lanes(), Error);
}

}  // namespace
}  // namespace flatslam
