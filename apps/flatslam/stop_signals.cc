#include "stop_signals.h"

#include <unistd.h>

#include <cstring>

namespace flatslam::app {

std::atomic<bool> g_stop{false};
volatile std::sig_atomic_t g_signal = 0;

namespace {

const char* g_command = "flatslam";

void WriteAll(const char* text) {
  (void)!::write(STDERR_FILENO, text, std::strlen(text));
}

extern "C" void OnStopSignal(int signal) {
  if (g_signal != 0) {
    WriteAll("\n");
    WriteAll(g_command);
    WriteAll(": second interrupt: exiting now\n");
    ::_exit(128 + signal);
  }
  g_signal = signal;
  g_stop.store(true);
  WriteAll("\n");
  WriteAll(g_command);
  WriteAll(
      ": interrupted: finishing the frames in flight, then writing the results (interrupt again to quit at "
      "once)\n");
}

}  // namespace

StopSignals::StopSignals(const char* command) {
  g_command = command;
  g_stop = false;
  g_signal = 0;
  struct sigaction action {};
  action.sa_handler = OnStopSignal;
  sigemptyset(&action.sa_mask);
  ::sigaction(SIGINT, &action, &old_int_);
  ::sigaction(SIGTERM, &action, &old_term_);
}

StopSignals::~StopSignals() {
  ::sigaction(SIGINT, &old_int_, nullptr);
  ::sigaction(SIGTERM, &old_term_, nullptr);
}

}  // namespace flatslam::app
