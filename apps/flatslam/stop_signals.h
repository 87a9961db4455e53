// SIGINT/SIGTERM for commands that keep their work when stopped (run, batch): the first signal
// sets g_stop, which the command passes to the run as its stop flag; a second one ends the
// process at once (files already in place stay complete: each is replaced atomically).
// Concurrency: the handler only writes g_signal, g_stop and stderr (async-signal-safe).
#pragma once

#include <signal.h>

#include <atomic>
#include <csignal>

namespace flatslam::app {

extern std::atomic<bool> g_stop;
extern volatile std::sig_atomic_t g_signal;  // the first signal received, 0 = none

// Installs the handler for SIGINT and SIGTERM while it lives; restores the previous handlers.
// `command` names the command in the messages (a string literal: it must outlive the object).
class StopSignals {
 public:
  explicit StopSignals(const char* command);
  ~StopSignals();
  StopSignals(const StopSignals&) = delete;
  StopSignals& operator=(const StopSignals&) = delete;

 private:
  struct sigaction old_int_ {
  }, old_term_{};
};

}  // namespace flatslam::app
