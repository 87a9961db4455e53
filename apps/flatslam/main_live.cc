// flatslam-live: the flatslam command line with DDS: `flatslam agent`, `flatslam server` and
// `flatslam run --publish` run here (flatslam hands them over, live.h). The other place (with
// main.cc) that picks the allocator.
#include <mimalloc-new-delete.h>

#include "dispatch.h"
#include "live.h"

int main(int argc, char** argv) {
  flatslam::app::EnableLive();
  return flatslam::app::Dispatch(argc, argv);
}
