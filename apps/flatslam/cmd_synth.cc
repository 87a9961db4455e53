// flatslam synth: render a synthetic scene; describe it or write it as a KITTI/TUM/EuRoC dataset.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <vector>

#include <opencv2/features2d.hpp>
#include <tbb/parallel_for.h>

#include "args.h"
#include "commands.h"
#include "io/dataset_writer.h"
#include "io/synthetic.h"

namespace flatslam::app {

const char* const kSynthUsage =
    "usage: flatslam synth [--scene SPEC] [--sensor mono|stereo|rgbd] [--seed N]\n"
    "                      [--out DIR --format kitti|tum|euroc] [--every N] [--list]\n\n"
    "Renders a synthetic scene with exact ground truth. Without --out it renders the\n"
    "sequence and prints what it holds (frames, path, loops, corners per frame, render speed);\n"
    "with --out it writes the sequence to DIR in a standard dataset layout.\n\n"
    "  --scene SPEC   NAME[:key=value,...]; NAME is room (default), corridor, street, town,\n"
    "                 highway or handheld; keys: width, height, fx, fps, duration, baseline,\n"
    "                 noise, depth_noise, agent, seed, sensor, dynamic (moving objects covering\n"
    "                 up to this fraction of the image, 0-0.3), rig_error (stereo: pixels added\n"
    "                 to every disparity, a real rig's rectification error, -5 to 5),\n"
    "                 structured_light (RGB-D: 1 = depth as a Kinect-class sensor reads it:\n"
    "                 quantized, shadowed beside nearer edges, edges fattened, 1 px off the\n"
    "                 colour image, 1% missing, none beyond 4.5 m), k1 (a radial distortion\n"
    "                 x (1 + k1 r^2) the images show and the calibration leaves out, 0-0.1).\n"
    "                 Example: town:agent=1,duration=30\n"
    "  --sensor S     mono, stereo (default) or rgbd\n"
    "  --seed N       noise seed (default 1); the world is fixed by the scene\n"
    "  --out DIR      write the dataset here (DIR must not exist or be empty)\n"
    "  --format F     kitti (mono/stereo), tum (rgbd/mono) or euroc (mono/stereo)\n"
    "  --every N      describe: analyse every N-th frame only (default 1)\n"
    "  --list         list the scenes and their agents\n";

namespace {

void ListScenes() {
  for (const std::string& name : SyntheticSceneNames()) {
    const SceneDescription scene = MakeScene(name);
    std::printf("%-9s %zu surfaces, %zu agent(s), default %.0f s\n", name.c_str(), scene.quads.size(),
                scene.agents.size(), scene.default_duration_s);
  }
}

int Describe(const SyntheticScene& scene, size_t every) {
  const Calibration& calib = scene.calibration();
  const SyntheticOptions& o = scene.options();
  std::printf("scene      %s, agent %d of %zu, %s\n", scene.description().name.c_str(), o.agent,
              scene.description().agents.size(), SensorName(o.sensor));
  std::printf("camera     %dx%d, fx %.1f fy %.1f cx %.1f cy %.1f", calib.camera.width, calib.camera.height,
              calib.camera.fx, calib.camera.fy, calib.camera.cx, calib.camera.cy);
  if (o.sensor == Sensor::kStereo) std::printf(", baseline %.3f m", calib.baseline_m);
  std::printf("\nframes     %zu at %.1f Hz (%.1f s)\n", scene.frame_count(), o.frame_rate_hz,
              scene.frame_count() / o.frame_rate_hz);
  std::printf("path       %.1f m, loop %.1f m, %.2f laps\n", scene.path_length_m(), scene.loop_length_m(),
              scene.path_length_m() / scene.loop_length_m());

  // Render the frames in parallel and count FAST corners: a check that the texture feeds ORB.
  std::vector<size_t> frames;
  for (size_t i = 0; i < scene.frame_count(); i += every) frames.push_back(i);
  std::vector<int> corners(frames.size());
  std::vector<double> valid_depth(frames.size(), 0.0);
  std::atomic<size_t> done{0};
  const auto start = std::chrono::steady_clock::now();
  tbb::parallel_for(size_t{0}, frames.size(), [&](size_t k) {
    const Frame f = scene.Render(frames[k]);
    std::vector<cv::KeyPoint> keypoints;
    cv::FAST(f.left, keypoints, 20, true);
    corners[k] = static_cast<int>(keypoints.size());
    if (!f.depth.empty()) valid_depth[k] = cv::countNonZero(f.depth > 0) / double(f.depth.total());
    const size_t n = ++done;
    if (n % 100 == 0) std::fprintf(stderr, "\rrendered %zu / %zu", n, frames.size());
  });
  const double seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::fprintf(stderr, "\r%40s\r", "");
  std::vector<int> sorted = corners;
  std::sort(sorted.begin(), sorted.end());
  std::printf("corners    FAST(20) per left image: min %d, median %d, max %d\n", sorted.front(),
              sorted[sorted.size() / 2], sorted.back());
  if (o.sensor == Sensor::kRgbd) {
    double sum = 0;
    for (double v : valid_depth) sum += v;
    std::printf("depth      %.1f%% of pixels have a measurement\n", 100.0 * sum / valid_depth.size());
  }
  std::printf("rendered   %zu frames in %.2f s on all cores (%.1f frames/s, with corner detection)\n", frames.size(),
              seconds, frames.size() / seconds);
  return 0;
}

}  // namespace

int RunSynth(const std::vector<std::string>& argv) {
  const Args args(argv, {"scene", "sensor", "seed", "out", "format", "every"}, {"list"});
  if (args.help()) {
    std::fputs(kSynthUsage, stdout);
    return 0;
  }
  if (!args.positional().empty()) throw UsageError{"unexpected argument '" + args.positional()[0] + "'"};
  if (args.has("list")) {
    ListScenes();
    return 0;
  }
  std::string scene_name;
  SyntheticOptions options;
  options.seed = static_cast<uint64_t>(args.get_int("seed", 1));
  if (auto s = args.get("sensor")) options.sensor = ParseSensor(*s);
  ParseSyntheticSpec(args.get_or("scene", "room"), &scene_name, &options);
  const int64_t every = args.get_int("every", 1);
  if (every < 1) throw UsageError{"--every must be at least 1"};
  if (args.has("format") && !args.has("out")) throw UsageError{"--format needs --out DIR"};

  const SyntheticScene scene(MakeScene(scene_name), options);
  if (!args.has("out")) return Describe(scene, static_cast<size_t>(every));

  if (!args.has("format")) throw UsageError{"--out needs --format kitti|tum|euroc"};
  const DatasetFormat format = ParseDatasetFormat(*args.get("format"));
  std::string spec = "synth:" + args.get_or("scene", "room");
  DatasetOptions dataset_options;
  dataset_options.seed = options.seed;
  dataset_options.sensor = options.sensor;
  const auto dataset = OpenDataset(spec, dataset_options);
  const auto result = WriteDataset(*dataset, *args.get("out"), format, [](size_t done, size_t total) {
    std::fprintf(stderr, "\rwriting %zu / %zu frames", done, total);
  });
  std::fprintf(stderr, "\n");
  std::printf("wrote %zu frames of %s to %s\nread it with: flatslam info %s\n", result.frames, dataset->name().c_str(),
              result.dataset_path.c_str(), result.dataset_path.c_str());
  return 0;
}

}  // namespace flatslam::app
