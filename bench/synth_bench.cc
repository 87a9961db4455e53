// Renderer throughput: frames per second per sensor on one thread, at each scene's camera
// (640x480; highway 1241x376); the *_portable rows shade and finish images without AVX2
// (the same pixels).
#include <benchmark/benchmark.h>

#include "io/synthetic.h"

namespace {

void BM_Render(benchmark::State& state, const char* scene, flatslam::Sensor sensor, bool avx2 = true) {
  flatslam::SyntheticOptions options;
  options.sensor = sensor;
  options.use_avx2 = avx2;
  flatslam::SyntheticScene synth(flatslam::MakeScene(scene), options);
  size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(synth.Render(i));
    i = (i + 7) % synth.frame_count();
  }
  state.counters["frames/s"] = benchmark::Counter(static_cast<double>(state.iterations()), benchmark::Counter::kIsRate);
}

BENCHMARK_CAPTURE(BM_Render, room_mono, "room", flatslam::Sensor::kMonocular)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, room_stereo, "room", flatslam::Sensor::kStereo)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, room_rgbd, "room", flatslam::Sensor::kRgbd)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, corridor_mono, "corridor", flatslam::Sensor::kMonocular)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, street_mono, "street", flatslam::Sensor::kMonocular)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, town_mono, "town", flatslam::Sensor::kMonocular)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, highway_stereo, "highway", flatslam::Sensor::kStereo)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, handheld_stereo, "handheld", flatslam::Sensor::kStereo)->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, room_stereo_portable, "room", flatslam::Sensor::kStereo, false)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, highway_stereo_portable, "highway", flatslam::Sensor::kStereo, false)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Render, handheld_stereo_portable, "handheld", flatslam::Sensor::kStereo, false)
    ->Unit(benchmark::kMillisecond);

}  // namespace

BENCHMARK_MAIN();
