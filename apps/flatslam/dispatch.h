// The flatslam command line: the subcommands and their dispatch, shared by the two executables
// (flatslam, and flatslam-live, which adds the DDS commands' implementation: live.h).
// Concurrency: called once from main.
#pragma once

namespace flatslam::app {

// Runs the subcommand argv[1] with the rest; returns the exit code (2 for bad usage).
int Dispatch(int argc, char** argv);

}  // namespace flatslam::app
