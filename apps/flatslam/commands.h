// The flatslam subcommands. Each takes the arguments after its name and returns the exit
// code; bad arguments throw UsageError, bad input throws flatslam::Error.
#pragma once

#include <string>
#include <vector>

namespace flatslam::app {

struct Command {
  const char* name;
  const char* summary;
  const char* usage;  // full help text for `flatslam <cmd> --help`
  int (*run)(const std::vector<std::string>& args);
};

int RunSynth(const std::vector<std::string>& args);
int RunEval(const std::vector<std::string>& args);
int RunInfo(const std::vector<std::string>& args);
int RunRun(const std::vector<std::string>& args);
int RunVocab(const std::vector<std::string>& args);
int RunMap(const std::vector<std::string>& args);
int RunBatch(const std::vector<std::string>& args);
int RunAgent(const std::vector<std::string>& args);
int RunServer(const std::vector<std::string>& args);

extern const char* const kSynthUsage;
extern const char* const kEvalUsage;
extern const char* const kInfoUsage;
extern const char* const kRunUsage;
extern const char* const kVocabUsage;
extern const char* const kMapUsage;
extern const char* const kBatchUsage;
extern const char* const kAgentUsage;
extern const char* const kServerUsage;

}  // namespace flatslam::app
