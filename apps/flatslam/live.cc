#include "live.h"

#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <optional>
#include <string_view>

#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "storage/snapshot.h"

namespace flatslam::app {

std::unique_ptr<AgentPublisher> (*g_make_agent_publisher)(uint32_t, const LiveOptions&, const AgentCamera&) = nullptr;
int (*g_run_server)(const std::vector<std::string>&) = nullptr;

const char* const kAgentUsage =
    "usage: flatslam agent DATASET --id N [--dds-domain D] [--dds-peers IP,...|multicast]\n"
    "                      [--wait-for-server S] [run options]\n\n"
    "Runs SLAM over DATASET as live agent N: flatslam run DATASET --agent N --publish (see flatslam run\n"
    "--help for the other options). Each frame's pose goes out as a ROS 2 geometry_msgs/PoseStamped on\n"
    "rt/flatslam/agent_N/pose (best effort), each keyframe the agent maps to flatslam/keyframes (reliable;\n"
    "a server that starts later gets the whole map again), and at the end every keyframe again as the\n"
    "agent's final map, then a message that its run ended; flatslam server collects them. Once the\n"
    "server has merged the agent's map with others', it sends corrections on flatslam/corrections and\n"
    "the agent publishes its poses in the merged map's frame (frame_id flatslam_map_<run>) instead of\n"
    "its own (flatslam_agent_N_map). The agent also moves its map into that frame (a monocular one with\n"
    "the merged map's scale), so that its saved map and trajectory are in it (--own-frame: its map stays\n"
    "in its own frame).\n"
    "The summary adds the bytes sent per keyframe and per second and the last correction. An agent that\n"
    "no server matched by its end says so on stderr; --wait-for-server S makes it wait up to S seconds\n"
    "for a first server at its end (default 0) and send that server its whole map.\n\n"
    "       flatslam agent --resume CHECKPOINT [--quiet]\n"
    "continues an agent that was stopped or killed from its --checkpoint (as flatslam run --resume\n"
    "does: its map, options and outputs, from the frame after the checkpoint). It publishes as a new\n"
    "run of the agent and tells each server it meets that this run replaces the stopped one: the\n"
    "server drops the stopped run's map and takes the resumed map's keyframes (those up to the\n"
    "checkpoint) from the new run; what the stopped run mapped after its checkpoint is gone with it.\n";

const char* const kServerUsage =
    "usage: flatslam server --out DIR [--vocabulary FILE] [--dds-domain D] [--dds-peers IP,...|multicast]\n"
    "                       [--agents N [--idle S]] [--live-merge S]\n\n"
    "Collects the keyframes that live agents publish (flatslam agent) into one map per agent run.\n"
    "While they arrive it merges copies of the maps in the background (at most every --live-merge S\n"
    "seconds, default 2, never sooner after a merge than it took; 0: only at the end), prints each\n"
    "agent run's first keyframe as it arrives, and when agents' maps meet and how long after their\n"
    "first overlap, and sends each merged agent a correction: where its map frame sits in the\n"
    "merged map, fitted on its 10 newest keyframes. Each merge also closes loops in the merged\n"
    "maps (as flatslam map merge --close-loops does). It\n"
    "stops on SIGINT or SIGTERM, or with --agents N once N agents were heard from and each has ended its\n"
    "newest run (a restarted agent starts a new run); with --idle S too, also once N agents were heard from\n"
    "and nothing came for S seconds (an agent that was killed never says it ended). It then merges the maps where "
    "place recognition finds them overlapping (as\n"
    "flatslam map merge does) and writes DIR/map.fsmap atomically: one map per group of agents that met.\n"
    "A malformed message is dropped with a warning naming its agent and sequence number.\n"
    "Exit code: 0, or 130/143 when stopped by SIGINT/SIGTERM (the map is written either way).\n";

namespace {

// One --id N out of the arguments (also --id=N).
std::string TakeId(std::vector<std::string>* argv) {
  for (size_t i = 0; i < argv->size(); ++i) {
    const std::string& a = (*argv)[i];
    if (a.rfind("--id=", 0) == 0) {
      std::string id = a.substr(5);
      argv->erase(argv->begin() + static_cast<std::ptrdiff_t>(i));
      return id;
    }
    if (a == "--id" && i + 1 < argv->size()) {
      std::string id = (*argv)[i + 1];
      argv->erase(argv->begin() + static_cast<std::ptrdiff_t>(i), argv->begin() + static_cast<std::ptrdiff_t>(i) + 2);
      return id;
    }
  }
  throw UsageError{"agent needs --id N"};
}

// The checkpoint named by --resume F (or --resume=F), if any.
std::optional<std::string> ResumeFile(const std::vector<std::string>& argv) {
  for (size_t i = 0; i < argv.size(); ++i) {
    if (argv[i].rfind("--resume=", 0) == 0) return argv[i].substr(9);
    if (argv[i] == "--resume" && i + 1 < argv.size()) return argv[i + 1];
  }
  return std::nullopt;
}

// Whether the run checkpointed in `file` published as a live agent (false when the file cannot be
// read: the resume reports that itself).
bool CheckpointPublishes(const std::string& file) {
  try {
    const std::optional<SnapshotSession> session = MapSnapshotView::Open(file).session_summary();
    if (!session) return false;
    for (const std::string& a : session->arguments)
      if (a == "--publish") return true;
  } catch (const std::exception&) {
  }
  return false;
}

}  // namespace

int RunAgent(const std::vector<std::string>& original) {
  for (const std::string& a : original)
    if (a == "--help" || a == "-h") {
      std::fputs(kAgentUsage, stdout);
      return 0;
    }
  // A stopped agent resumed from its checkpoint: the checkpoint holds its --agent and --publish.
  if (const std::optional<std::string> file = ResumeFile(original)) {
    FLATSLAM_CHECK(!std::filesystem::exists(*file) || CheckpointPublishes(*file), "agent --resume ", *file,
                   ": not the checkpoint of an agent (continue it with flatslam run --resume)");
    return RunRun(original);
  }
  std::vector<std::string> argv = original;
  const std::string id = TakeId(&argv);
  for (const std::string& a : argv)
    if (a == "--agent" || a.rfind("--agent=", 0) == 0 || a == "--publish")
      throw UsageError{"agent sets --agent and --publish itself (from --id)"};
  argv.push_back("--agent=" + id);
  argv.push_back("--publish");
  return RunRun(argv);
}

int RunServer(const std::vector<std::string>& args) {
  for (const std::string& a : args)
    if (a == "--help" || a == "-h") {
      std::fputs(kServerUsage, stdout);
      return 0;
    }
  FLATSLAM_CHECK(g_run_server != nullptr, "this executable has no DDS support (run flatslam-live)");
  return g_run_server(args);
}

bool NeedsLive(int argc, char** argv) {
  if (argc < 2) return false;
  const std::string_view command = argv[1];
  bool help = false, publish = false;
  for (int i = 2; i < argc; ++i) {
    const std::string_view a = argv[i];
    help = help || a == "--help" || a == "-h";
    publish = publish || a == "--publish";
  }
  if (help) return false;  // the usage text is here too
  if (command == "run" && !publish) {
    // A resumed run publishes when the run it continues did.
    std::vector<std::string> args(argv + 2, argv + argc);
    if (const std::optional<std::string> file = ResumeFile(args)) publish = CheckpointPublishes(*file);
  }
  return command == "agent" || command == "server" || (command == "run" && publish);
}

void ExecLive(int argc, char** argv) {
  std::error_code ec;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
  const std::filesystem::path live = (ec ? std::filesystem::path(argv[0]) : self).parent_path() / "flatslam-live";
  std::vector<char*> args(argv, argv + argc);
  args[0] = const_cast<char*>(live.c_str());
  args.push_back(nullptr);
  ::execv(live.c_str(), args.data());
  std::fprintf(stderr, "flatslam %s: cannot start %s (%s): this build has no DDS support\n", argv[1], live.c_str(),
               std::strerror(errno));
  std::exit(1);
}

}  // namespace flatslam::app
