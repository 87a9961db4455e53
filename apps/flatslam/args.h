// Minimal command-line parsing for flatslam subcommands: positionals and --key value flags.
// Concurrency: plain values.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <vector>

namespace flatslam::app {

// Thrown for bad arguments; main prints it with the command's usage and exits with 2.
struct UsageError {
  std::string message;
};

class Args {
 public:
  // flags: names (without "--") that take a value; switches: names that take none; lists: flags
  // that may be given more than once, their values joined by commas in the order given
  // (`--set a=1 --set b=2` reads as `--set a=1,b=2`). Any other flag given twice with two values
  // is a UsageError naming both, so that no value is dropped unseen; a switch may repeat.
  Args(const std::vector<std::string>& argv, const std::set<std::string>& flags, const std::set<std::string>& switches,
       const std::set<std::string>& lists = {});

  [[nodiscard]] const std::vector<std::string>& positional() const { return positional_; }
  [[nodiscard]] bool has(const std::string& name) const { return values_.count(name) > 0; }
  [[nodiscard]] std::optional<std::string> get(const std::string& name) const;
  [[nodiscard]] std::string get_or(const std::string& name, const std::string& fallback) const;
  [[nodiscard]] double get_double(const std::string& name, double fallback) const;
  [[nodiscard]] int64_t get_int(const std::string& name, int64_t fallback) const;
  [[nodiscard]] bool help() const { return help_; }

 private:
  std::vector<std::string> positional_;
  std::map<std::string, std::string> values_;
  bool help_ = false;
};

}  // namespace flatslam::app
