// flatslam info: open any dataset through the common reader interface and describe it.
#include <atomic>
#include <chrono>
#include <cstdio>
#include <mutex>
#include <string>

#include <tbb/parallel_for.h>

#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "io/dataset.h"
#include "io/orb_settings.h"

namespace flatslam::app {

const char* const kInfoUsage =
    "usage: flatslam info DATASET [--sensor mono|stereo|rgbd] [--seed N] [--settings FILE] [--check]\n\n"
    "Opens a dataset and prints its sensor, calibration, frame count, duration and ground truth.\n"
    "DATASET is a KITTI sequence folder (.../sequences/NN), an EuRoC sequence (the folder\n"
    "holding mav0/), a TUM RGB-D sequence (the folder holding rgb.txt), synth:SPEC, or a folder of\n"
    "images (with --settings).\n"
    "  --settings FILE  an ORB-SLAM2/3 settings YAML whose camera replaces the dataset's calibration\n"
    "  --check   read every frame (in parallel) and report the first bad image\n";

int RunInfo(const std::vector<std::string>& argv) {
  const Args args(argv, {"sensor", "seed", "settings"}, {"check"});
  if (args.help()) {
    std::fputs(kInfoUsage, stdout);
    return 0;
  }
  if (args.positional().size() != 1) throw UsageError{"expected exactly one DATASET"};
  DatasetOptions options;
  if (auto s = args.get("sensor")) options.sensor = ParseSensor(*s);
  options.seed = static_cast<uint64_t>(args.get_int("seed", 1));
  if (auto s = args.get("settings")) options.settings = std::make_shared<const OrbSettings>(ReadOrbSettings(*s));
  const auto dataset = OpenDataset(args.positional()[0], options);
  const Calibration& calib = dataset->calibration();
  FLATSLAM_CHECK(dataset->size() > 0, "dataset ", args.positional()[0], " has no frames");
  const Frame first = dataset->read(0);
  const Frame last = dataset->read(dataset->size() - 1);

  std::printf("dataset    %s\n", dataset->name().c_str());
  std::printf("sensor     %s\n", SensorName(calib.sensor));
  std::printf("camera     %dx%d, fx %.3f fy %.3f cx %.3f cy %.3f", calib.camera.width, calib.camera.height,
              calib.camera.fx, calib.camera.fy, calib.camera.cx, calib.camera.cy);
  if (calib.sensor == Sensor::kStereo) std::printf(", baseline %.4f m", calib.baseline_m);
  std::printf("\nframes     %zu, %.3f s", dataset->size(), (last.t_ns - first.t_ns) * 1e-9);
  if (calib.frame_rate_hz > 0) std::printf(" (nominal %.1f Hz)", calib.frame_rate_hz);
  std::printf("\n");
  if (auto gt = dataset->ground_truth()) {
    double length = 0;
    for (size_t i = 1; i < gt->size(); ++i)
      length += ((*gt)[i].T_world_cam.translation() - (*gt)[i - 1].T_world_cam.translation()).norm();
    std::printf("truth      %zu poses, path %.2f m\n", gt->size(), length);
  } else {
    std::printf("truth      none\n");
  }

  if (args.has("check")) {
    std::atomic<size_t> read{0};
    std::mutex mutex;
    std::string first_error;
    const auto start = std::chrono::steady_clock::now();
    tbb::parallel_for(size_t{0}, dataset->size(), [&](size_t i) {
      try {
        (void)dataset->read(i);
        ++read;
      } catch (const Error& e) {
        std::lock_guard<std::mutex> lock(mutex);
        if (first_error.empty()) first_error = e.what();
      }
    });
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (!first_error.empty()) {
      std::printf("check      %zu of %zu frames read; first error: %s\n", read.load(), dataset->size(),
                  first_error.c_str());
      return 1;
    }
    std::printf("check      all %zu frames read in %.2f s\n", dataset->size(), s);
  }
  return 0;
}

}  // namespace flatslam::app
