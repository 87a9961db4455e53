// The flatslam command line's dispatch to subcommands, shared by flatslam and flatslam-live.
#include "dispatch.h"

#include <mimalloc.h>

#include <cstdio>
#include <cstdlib>
#include <exception>
#include <string>
#include <vector>

#include "args.h"
#include "commands.h"
#include "core/error.h"

namespace {

using flatslam::app::Command;

const Command kCommands[] = {
    {"synth", "render a synthetic scene, print what it holds or write it as a dataset", flatslam::app::kSynthUsage,
     flatslam::app::RunSynth},
    {"info", "open a dataset (KITTI, EuRoC, TUM RGB-D or synth:NAME) and describe it", flatslam::app::kInfoUsage,
     flatslam::app::RunInfo},
    {"run", "SLAM over a dataset: trajectory, keyframes, per-frame stats, accuracy", flatslam::app::kRunUsage,
     flatslam::app::RunRun},
    {"batch", "many sequences at once on every core: one results table, one report, shards", flatslam::app::kBatchUsage,
     flatslam::app::RunBatch},
    {"eval", "ATE, RPE and KITTI metrics of an estimated trajectory against ground truth", flatslam::app::kEvalUsage,
     flatslam::app::RunEval},
    {"vocab", "train a bag-of-words vocabulary from images, or describe a vocabulary file", flatslam::app::kVocabUsage,
     flatslam::app::RunVocab},
    {"map", "describe, verify or export a map snapshot (info, verify, export)", flatslam::app::kMapUsage,
     flatslam::app::RunMap},
    {"agent", "SLAM as a live agent: poses and keyframes published on DDS", flatslam::app::kAgentUsage,
     flatslam::app::RunAgent},
    {"server", "collect live agents' keyframes over DDS and merge their maps", flatslam::app::kServerUsage,
     flatslam::app::RunServer},
};

void PrintHelp(std::FILE* out) {
  std::fprintf(out,
               "flatslam: visual SLAM (monocular, stereo, RGB-D)\n\n"
               "usage: flatslam <command> [options]   (flatslam <command> --help for details)\n\n"
               "commands:\n");
  for (const Command& c : kCommands) std::fprintf(out, "  %-8s %s\n", c.name, c.summary);
  std::fprintf(out, "  %-8s %s\n", "help", "show this text");
}

}  // namespace

namespace flatslam::app {

int Dispatch(int argc, char** argv) {
  // Memory the program frees goes back to the system half a second after it was last used, so a
  // session that runs for hours keeps a flat resident set, while the buffers every frame and
  // keyframe frees and allocates again (pyramids, matching, bundle adjustment) are reused
  // instead of being returned and faulted in again on the next frame: half a second covers
  // several frames at the 10-30 Hz of the cameras supported and a keyframe's mapping. Returning
  // pages at once (page reset, no delay) cost 20-40% of the run in page faults (room stereo 101
  // against 140 frames/s); docs/STATUS.md has the figures, resident sets included. The
  // environment (MIMALLOC_PAGE_RESET, MIMALLOC_DECOMMIT_DELAY) can still override both.
  if (!std::getenv("MIMALLOC_DECOMMIT_DELAY") && !std::getenv("MIMALLOC_RESET_DELAY"))
    mi_option_set(mi_option_decommit_delay, 500);
  std::vector<std::string> args(argv + 1, argv + argc);
  if (args.empty()) {
    PrintHelp(stderr);
    return 2;
  }
  const std::string name = args.front();
  if (name == "help" || name == "--help" || name == "-h") {
    if (args.size() > 1) {
      for (const Command& c : kCommands) {
        if (args[1] == c.name) {
          std::fputs(c.usage, stdout);
          return 0;
        }
      }
    }
    PrintHelp(stdout);
    return 0;
  }
  for (const Command& c : kCommands) {
    if (name != c.name) continue;
    std::vector<std::string> rest(args.begin() + 1, args.end());
    try {
      return c.run(rest);
    } catch (const flatslam::app::UsageError& e) {
      std::fprintf(stderr, "flatslam %s: %s\n\n%s", c.name, e.message.c_str(), c.usage);
      return 2;
    } catch (const flatslam::Error& e) {
      std::fprintf(stderr, "flatslam %s: error: %s\n", c.name, e.what());
      // Where the failing check is, for a bug report.
      if (*e.where() != '\0') std::fprintf(stderr, "  (check failed at %s)\n", e.where());
      return 1;
    } catch (const std::exception& e) {
      std::fprintf(stderr, "flatslam %s: unexpected error: %s\n", c.name, e.what());
      return 1;
    }
  }
  std::fprintf(stderr, "flatslam: unknown command '%s'\n\n", name.c_str());
  PrintHelp(stderr);
  return 2;
}

}  // namespace flatslam::app
