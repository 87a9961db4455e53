// flatslam: the command line without DDS's libraries. The DDS commands (agent, server, run
// --publish) are handed to flatslam-live, so that no other run maps them (live.h). One of the two
// places (with main_live.cc) that picks the allocator.
#include <mimalloc-new-delete.h>

#include "dispatch.h"
#include "live.h"

int main(int argc, char** argv) {
  if (flatslam::app::NeedsLive(argc, argv)) flatslam::app::ExecLive(argc, argv);
  return flatslam::app::Dispatch(argc, argv);
}
