// Running the flatslam executable from tests: exit code and combined output of one command line.
#pragma once

#include <fcntl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "test_data.h"

namespace flatslam::testing {

struct CliResult {
  int exit_code = -1;
  std::string output;  // stdout and stderr
};

// Runs a shell command line, stdout and stderr together.
inline CliResult RunCommand(const std::string& command_line) {
  const std::string command = command_line + " 2>&1";
  CliResult result;
  FILE* pipe = popen(command.c_str(), "r");
  if (!pipe) return result;
  std::array<char, 4096> buffer;
  size_t n;
  while ((n = fread(buffer.data(), 1, buffer.size(), pipe)) > 0) result.output.append(buffer.data(), n);
  const int status = pclose(pipe);
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return result;
}

// Runs `flatslam ARGUMENTS` through the shell (so arguments may hold quotes and redirections).
inline CliResult RunApp(const std::string& arguments) {
  return RunCommand(AppPath() + " " + arguments);
}

// Starts `flatslam ARGS` in the background with stdout and stderr going to `log`.
inline pid_t Spawn(const std::vector<std::string>& args, const std::filesystem::path& log) {
  const std::string app = AppPath();
  std::vector<std::string> all = {app};
  all.insert(all.end(), args.begin(), args.end());
  const pid_t pid = ::fork();
  if (pid == 0) {
    const int fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    ::dup2(fd, STDOUT_FILENO);
    ::dup2(fd, STDERR_FILENO);
    std::vector<char*> argv;
    for (std::string& a : all) argv.push_back(a.data());
    argv.push_back(nullptr);
    ::execv(app.c_str(), argv.data());
    ::_exit(127);
  }
  return pid;
}

// Exit code of a spawned child, or 128 + signal for one killed by a signal.
inline int Wait(pid_t pid) {
  int status = 0;
  if (::waitpid(pid, &status, 0) != pid) return -1;
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  return WIFSIGNALED(status) ? 128 + WTERMSIG(status) : -1;
}

inline bool Contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

// The number after the first occurrence of `key` in text, such as a run's summary (NaN when absent).
inline double NumberAfter(const std::string& text, const std::string& key) {
  const size_t at = text.find(key);
  return at == std::string::npos ? std::nan("") : std::stod(text.substr(at + key.size()));
}

}  // namespace flatslam::testing
