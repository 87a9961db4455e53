// Map snapshot save / read-only open / full load on a KITTI-00-sized synthetic map (1,400
// keyframes x 2,000 keypoints, 140,000 map points, ~10 observations each), built directly through
// the Map API. Reference (ORB-SLAM2, Boost binary): save 2.58 s, load 2.64 s, 410 MiB.
// Run: bench_snapshot [--benchmark_filter=...] [--benchmark_repetitions=N]
//      (FLATSLAM_BENCH_DIR picks the directory for the file; default: the system temp dir)
//      bench_snapshot --first-save FILE: builds the map, saves it once and prints the time: the
//      first save of a process, which repeated iterations cannot show (bench/snapshot_first_save.sh).
#include <fcntl.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>

#include <benchmark/benchmark.h>

#include "storage/random_map.h"
#include "storage/snapshot.h"

namespace flatslam {
namespace {

const Map& KittiSizedMap() {
  static const Map map = [] {
    testing::RandomMapOptions o;
    o.keyframes = 1401;  // RandomMap erases one
    o.keypoints = 2000;
    o.points = 140000;
    o.observations_per_point = 10;
    o.loop_edges = 4;
    o.agents = 1;
    return testing::RandomMap(o);
  }();
  return map;
}

std::filesystem::path SnapshotPath() {
  const char* dir = std::getenv("FLATSLAM_BENCH_DIR");
  const std::filesystem::path base = dir ? std::filesystem::path(dir) : std::filesystem::temp_directory_path();
  return base / ("flatslam_bench_snapshot_" + std::to_string(::getpid()) + ".fsmap");
}

SnapshotMetadata Metadata();

// The snapshot the read benchmarks open, saved first when an earlier benchmark did not.
std::filesystem::path SavedSnapshot() {
  const auto path = SnapshotPath();
  if (!std::filesystem::exists(path)) {
    const SnapshotMapRef ref{0, &KittiSizedMap()};
    SaveMapSnapshot(path, {&ref, 1}, Metadata());
  }
  return path;
}

// The saved snapshot, read through once so that its pages are in the page cache (saves write
// around the cache, with direct I/O).
std::filesystem::path CachedSnapshot() {
  const auto path = SavedSnapshot();
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f) {
    static char chunk[1 << 20];
    while (std::fread(chunk, 1, sizeof(chunk), f) == sizeof(chunk)) {
    }
    std::fclose(f);
  }
  return path;
}

// Drops the file's pages from the page cache (clean pages: no privileges needed).
void EvictFromCache(const std::filesystem::path& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return;
  (void)::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED);
  ::close(fd);
}

SnapshotMetadata Metadata() {
  SnapshotMetadata m;
  m.calibration.sensor = Sensor::kStereo;
  m.calibration.camera = {718.856, 718.856, 607.19, 185.22, 1241, 376};
  m.calibration.baseline_m = 0.537;
  m.calibration.frame_rate_hz = 10;
  return m;
}

void SetMapCounters(benchmark::State& state, const std::filesystem::path& path) {
  const Map& map = KittiSizedMap();
  size_t observations = 0;
  for (const MapPoint& p : map.points().values()) observations += p.observations.size();
  state.counters["keyframes"] = static_cast<double>(map.keyframes().size());
  state.counters["points"] = static_cast<double>(map.points().size());
  state.counters["observations"] = static_cast<double>(observations);
  if (std::filesystem::exists(path))
    state.counters["file_MiB"] = static_cast<double>(std::filesystem::file_size(path)) / 1048576.0;
}

// Serialization only (no disk).
void BM_Serialize(benchmark::State& state) {
  const Map& map = KittiSizedMap();
  const SnapshotMapRef ref{0, &map};
  size_t bytes = 0;
  for (auto _ : state) {
    const std::vector<uint8_t> buffer = SerializeMapSnapshot({&ref, 1}, Metadata());
    bytes = buffer.size();
    benchmark::DoNotOptimize(buffer.data());
  }
  state.counters["MiB"] = static_cast<double>(bytes) / 1048576.0;
}
BENCHMARK(BM_Serialize)->Unit(benchmark::kMillisecond)->Iterations(5);

// The full atomic save: serialize, write a temporary, fsync, rename, fsync the directory.
// Each iteration replaces the file the previous one wrote (a periodic save).
void BM_Save(benchmark::State& state) {
  const Map& map = KittiSizedMap();
  const SnapshotMapRef ref{0, &map};
  const auto path = SnapshotPath();
  for (auto _ : state) SaveMapSnapshot(path, {&ref, 1}, Metadata());
  SetMapCounters(state, path);
}
BENCHMARK(BM_Save)->Unit(benchmark::kMillisecond)->Iterations(5);

// The same save to a path where no file exists yet (the previous one is removed untimed).
void BM_SaveNewFile(benchmark::State& state) {
  const Map& map = KittiSizedMap();
  const SnapshotMapRef ref{0, &map};
  auto path = SnapshotPath();
  path += ".new";
  for (auto _ : state) {
    state.PauseTiming();
    std::filesystem::remove(path);
    state.ResumeTiming();
    SaveMapSnapshot(path, {&ref, 1}, Metadata());
  }
  SetMapCounters(state, path);
  std::filesystem::remove(path);
}
BENCHMARK(BM_SaveNewFile)->Unit(benchmark::kMillisecond)->Iterations(5);

// Read-only open: mmap + verification of structure and every index (file in the page cache).
void BM_OpenReadOnly(benchmark::State& state) {
  const auto path = CachedSnapshot();
  SnapshotReadOptions options;
  options.verify_content_hash = false;
  for (auto _ : state) {
    const MapSnapshotView view = MapSnapshotView::Open(path, options);
    benchmark::DoNotOptimize(view.point_count(0));
  }
}
BENCHMARK(BM_OpenReadOnly)->Unit(benchmark::kMillisecond)->Iterations(20);

// The same open with the file's pages evicted before each iteration: read from the disk, as the
// first open after a reboot (or after a save, which bypasses the cache).
void BM_OpenReadOnlyCold(benchmark::State& state) {
  const auto path = SavedSnapshot();
  SnapshotReadOptions options;
  options.verify_content_hash = false;
  for (auto _ : state) {
    state.PauseTiming();
    EvictFromCache(path);
    state.ResumeTiming();
    const MapSnapshotView view = MapSnapshotView::Open(path, options);
    benchmark::DoNotOptimize(view.point_count(0));
  }
}
BENCHMARK(BM_OpenReadOnlyCold)->Unit(benchmark::kMillisecond)->Iterations(5);

// Read-only open that also hashes every byte (what `map verify` and loading do).
void BM_OpenWithContentHash(benchmark::State& state) {
  const auto path = CachedSnapshot();
  for (auto _ : state) {
    const MapSnapshotView view = MapSnapshotView::Open(path);
    benchmark::DoNotOptimize(view.point_count(0));
  }
}
BENCHMARK(BM_OpenWithContentHash)->Unit(benchmark::kMillisecond)->Iterations(10);

// Full load into fresh arenas, content hash and Map::Validate() included.
void BM_Load(benchmark::State& state) {
  const auto path = CachedSnapshot();
  for (auto _ : state) {
    LoadedSnapshot loaded = LoadMapSnapshot(path);
    benchmark::DoNotOptimize(loaded.maps[0].map.points().size());
  }
  SetMapCounters(state, path);
  std::filesystem::remove(path);
}
BENCHMARK(BM_Load)->Unit(benchmark::kMillisecond)->Iterations(5);

}  // namespace
}  // namespace flatslam

int main(int argc, char** argv) {
  if (argc == 3 && std::strcmp(argv[1], "--first-save") == 0) {
    const flatslam::Map& map = flatslam::KittiSizedMap();
    const flatslam::SnapshotMapRef ref{0, &map};
    const auto start = std::chrono::steady_clock::now();
    flatslam::SaveMapSnapshot(argv[2], {&ref, 1}, flatslam::Metadata());
    std::printf("first save %.1f ms, %.1f MiB\n",
                std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count(),
                static_cast<double>(std::filesystem::file_size(argv[2])) / 1048576.0);
    return 0;
  }
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
