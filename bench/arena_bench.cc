// Arena<T> against std::unordered_map<uint64_t, T> and new/delete'd pointer-linked nodes:
// create/erase churn, iteration, and heap bytes (global operator new is replaced below).
// Run: bench_arena [--benchmark_filter=...]; prints the process peak RSS at the end.
#include <malloc.h>
#include <sys/resource.h>

#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <new>
#include <unordered_map>
#include <vector>

#include <benchmark/benchmark.h>

#include "ecs/arena.h"

// ---------------------------------------------------------------------------------------
// Heap accounting. Off by default so that timing benchmarks pay only a relaxed load;
// the memory benchmarks switch it on around the code they measure.

namespace {
std::atomic<bool> g_tracking{false};
std::atomic<int64_t> g_current_bytes{0};
std::atomic<int64_t> g_peak_bytes{0};

void OnAllocate(void* p) {
  if (!g_tracking.load(std::memory_order_relaxed)) return;
  const auto bytes = static_cast<int64_t>(malloc_usable_size(p));
  const int64_t now = g_current_bytes.fetch_add(bytes, std::memory_order_relaxed) + bytes;
  int64_t peak = g_peak_bytes.load(std::memory_order_relaxed);
  while (now > peak && !g_peak_bytes.compare_exchange_weak(peak, now, std::memory_order_relaxed)) {
  }
}

void OnFree(void* p) {
  if (p == nullptr || !g_tracking.load(std::memory_order_relaxed)) return;
  g_current_bytes.fetch_sub(static_cast<int64_t>(malloc_usable_size(p)), std::memory_order_relaxed);
}

void* Allocate(size_t size) {
  void* p = std::malloc(size == 0 ? 1 : size);
  if (p != nullptr) OnAllocate(p);
  return p;
}

void* AllocateAligned(size_t size, std::align_val_t align) {
  const auto a = static_cast<size_t>(align);
  const size_t rounded = size == 0 ? a : (size + a - 1) / a * a;  // aligned_alloc wants a multiple
  void* p = std::aligned_alloc(a, rounded);
  if (p != nullptr) OnAllocate(p);
  return p;
}

// GCC cannot see that operator new above is malloc-backed and warns on the pairing.
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmismatched-new-delete"
void Free(void* p) {
  OnFree(p);
  std::free(p);
}
#pragma GCC diagnostic pop

// Starts counting heap bytes from zero at construction; stops at destruction.
class HeapMeter {
 public:
  HeapMeter() {
    g_current_bytes = 0;
    g_peak_bytes = 0;
    g_tracking = true;
  }
  ~HeapMeter() { g_tracking = false; }
  HeapMeter(const HeapMeter&) = delete;
  HeapMeter& operator=(const HeapMeter&) = delete;

  [[nodiscard]] int64_t current() const { return g_current_bytes.load(); }
  [[nodiscard]] int64_t peak() const { return g_peak_bytes.load(); }
};
}  // namespace

void* operator new(size_t size) {
  if (void* p = Allocate(size)) return p;
  throw std::bad_alloc();
}
void* operator new[](size_t size) {
  if (void* p = Allocate(size)) return p;
  throw std::bad_alloc();
}
void* operator new(size_t size, const std::nothrow_t&) noexcept {
  return Allocate(size);
}
void* operator new[](size_t size, const std::nothrow_t&) noexcept {
  return Allocate(size);
}
void* operator new(size_t size, std::align_val_t align) {
  if (void* p = AllocateAligned(size, align)) return p;
  throw std::bad_alloc();
}
void* operator new[](size_t size, std::align_val_t align) {
  if (void* p = AllocateAligned(size, align)) return p;
  throw std::bad_alloc();
}
void* operator new(size_t size, std::align_val_t align, const std::nothrow_t&) noexcept {
  return AllocateAligned(size, align);
}
void* operator new[](size_t size, std::align_val_t align, const std::nothrow_t&) noexcept {
  return AllocateAligned(size, align);
}
void operator delete(void* p) noexcept {
  Free(p);
}
void operator delete[](void* p) noexcept {
  Free(p);
}
void operator delete(void* p, size_t) noexcept {
  Free(p);
}
void operator delete[](void* p, size_t) noexcept {
  Free(p);
}
void operator delete(void* p, const std::nothrow_t&) noexcept {
  Free(p);
}
void operator delete[](void* p, const std::nothrow_t&) noexcept {
  Free(p);
}
void operator delete(void* p, std::align_val_t) noexcept {
  Free(p);
}
void operator delete[](void* p, std::align_val_t) noexcept {
  Free(p);
}
void operator delete(void* p, size_t, std::align_val_t) noexcept {
  Free(p);
}
void operator delete[](void* p, size_t, std::align_val_t) noexcept {
  Free(p);
}
void operator delete(void* p, std::align_val_t, const std::nothrow_t&) noexcept {
  Free(p);
}
void operator delete[](void* p, std::align_val_t, const std::nothrow_t&) noexcept {
  Free(p);
}

namespace flatslam {
namespace {

// A map-point-sized record: 64 bytes, one cache line. Every store builds it in place
// from the id, so construction costs the same everywhere.
struct Payload {
  Payload() = default;
  explicit Payload(uint64_t id_in)
      : position{double(id_in), double(id_in) + 1, double(id_in) + 2},
        normal{0.0, 0.0, 1.0},
        observations(id_in & 15u),
        id(id_in) {}

  double position[3] = {};
  double normal[3] = {};
  uint64_t observations = 0;
  uint64_t id = 0;
};
static_assert(sizeof(Payload) == 64);

// splitmix64: cheap, seeded, the same sequence for every store.
class Rng {
 public:
  explicit Rng(uint64_t seed) : state_(seed) {}
  uint64_t next() {
    uint64_t z = (state_ += 0x9e3779b97f4a7c15ull);
    z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
    z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
    return z ^ (z >> 31);
  }
  // Uniform in [0, n) by multiply-shift.
  size_t below(size_t n) { return static_cast<size_t>((static_cast<unsigned __int128>(next()) * n) >> 64); }

 private:
  uint64_t state_;
};

// Each store: create(id), erase_random(rng) of a uniformly chosen live entity, sum()
// over every live entity. reserve_index(n) sizes the caller-side id list (not part of
// the store) before heap metering starts, so only the store's own bytes are counted.

class ArenaStore {
 public:
  void reserve_index(size_t) {}
  void create(uint64_t id) { (void)arena_.create(id); }
  // Arena keeps its handles packed, so a random live handle needs no side list.
  void erase_random(Rng& rng) { arena_.erase(arena_.handles()[rng.below(arena_.size())]); }
  [[nodiscard]] uint64_t sum() const {
    uint64_t total = 0;
    for (const Payload& p : arena_.values()) total += p.observations;
    return total;
  }
  [[nodiscard]] size_t size() const { return arena_.size(); }

 private:
  Arena<Payload> arena_;
};

class HashMapStore {
 public:
  void reserve_index(size_t n) { ids_.reserve(n); }
  void create(uint64_t id) {
    map_.try_emplace(id, id);
    ids_.push_back(id);
  }
  void erase_random(Rng& rng) {
    const size_t k = rng.below(ids_.size());
    map_.erase(ids_[k]);
    ids_[k] = ids_.back();
    ids_.pop_back();
  }
  [[nodiscard]] uint64_t sum() const {
    uint64_t total = 0;
    for (const auto& [id, p] : map_) total += p.observations;
    return total;
  }
  [[nodiscard]] size_t size() const { return map_.size(); }

 private:
  std::unordered_map<uint64_t, Payload> map_;
  std::vector<uint64_t> ids_;  // caller-side id list for random picks
};

// One heap node per entity in an intrusive doubly-linked list, the pointer-graph layout.
class LinkedNodeStore {
 public:
  LinkedNodeStore() { head_.prev = head_.next = &head_; }
  ~LinkedNodeStore() {
    for (Node* n = head_.next; n != &head_;) {
      Node* next = n->next;
      delete n;
      n = next;
    }
  }
  LinkedNodeStore(const LinkedNodeStore&) = delete;
  LinkedNodeStore& operator=(const LinkedNodeStore&) = delete;

  void reserve_index(size_t n) { nodes_.reserve(n); }
  void create(uint64_t id) {
    Node* n = new Node{head_.prev, &head_, Payload(id)};
    head_.prev->next = n;
    head_.prev = n;
    nodes_.push_back(n);
  }
  void erase_random(Rng& rng) {
    const size_t k = rng.below(nodes_.size());
    Node* n = nodes_[k];
    n->prev->next = n->next;
    n->next->prev = n->prev;
    delete n;
    nodes_[k] = nodes_.back();
    nodes_.pop_back();
  }
  [[nodiscard]] uint64_t sum() const {
    uint64_t total = 0;
    for (const Node* n = head_.next; n != &head_; n = n->next) total += n->value.observations;
    return total;
  }
  [[nodiscard]] size_t size() const { return nodes_.size(); }

 private:
  struct Node {
    Node* prev;
    Node* next;
    Payload value;
  };
  Node head_{nullptr, nullptr, {}};
  std::vector<Node*> nodes_;  // caller-side pointer list for random picks
};

using Clock = std::chrono::steady_clock;

double Nanoseconds(Clock::time_point start, Clock::time_point stop) {
  return std::chrono::duration<double, std::nano>(stop - start).count();
}

constexpr uint64_t kSeed = 0x5eed;

// Fill n entities, then n rounds of (erase a random live entity, create a new one).
// Manual time covers the churn rounds only; ns_per_op is one erase plus one create.
template <class Store>
void BM_Churn(benchmark::State& state) {
  const auto n = static_cast<size_t>(state.range(0));
  double churn_ns = 0.0;
  double fill_ns = 0.0;
  for (auto _ : state) {
    auto store = std::make_unique<Store>();
    store->reserve_index(n);
    Rng rng(kSeed);
    uint64_t next_id = 0;
    const auto t0 = Clock::now();
    for (size_t i = 0; i < n; ++i) store->create(next_id++);
    const auto t1 = Clock::now();
    for (size_t i = 0; i < n; ++i) {
      store->erase_random(rng);
      store->create(next_id++);
    }
    const auto t2 = Clock::now();
    benchmark::DoNotOptimize(store->size());
    fill_ns += Nanoseconds(t0, t1);
    churn_ns += Nanoseconds(t1, t2);
    state.SetIterationTime(Nanoseconds(t1, t2) * 1e-9);
  }
  const double ops = static_cast<double>(n) * static_cast<double>(state.iterations());
  state.counters["churn_ns_per_op"] = churn_ns / ops;
  state.counters["fill_ns_per_create"] = fill_ns / ops;
}

// Sum one field over n live entities that went through n churn rounds first (so node
// stores are scattered over the heap the way a long run leaves them).
template <class Store>
void BM_Iterate(benchmark::State& state) {
  const auto n = static_cast<size_t>(state.range(0));
  Store store;
  store.reserve_index(n);
  Rng rng(kSeed);
  uint64_t next_id = 0;
  for (size_t i = 0; i < n; ++i) store.create(next_id++);
  for (size_t i = 0; i < n; ++i) {
    store.erase_random(rng);
    store.create(next_id++);
  }
  double total_ns = 0.0;
  for (auto _ : state) {
    const auto t0 = Clock::now();
    benchmark::DoNotOptimize(store.sum());
    const auto t1 = Clock::now();
    total_ns += Nanoseconds(t0, t1);
    state.SetIterationTime(Nanoseconds(t0, t1) * 1e-9);
  }
  state.counters["ns_per_element"] = total_ns / (static_cast<double>(n) * static_cast<double>(state.iterations()));
}

// Heap bytes held by the store: peak over fill + churn, and what stays live after churn.
template <class Store>
void BM_Memory(benchmark::State& state) {
  const auto n = static_cast<size_t>(state.range(0));
  int64_t peak = 0;
  int64_t live = 0;
  for (auto _ : state) {
    Rng rng(kSeed);
    uint64_t next_id = 0;
    auto store = std::make_unique<Store>();
    store->reserve_index(n);
    {
      const HeapMeter meter;
      for (size_t i = 0; i < n; ++i) store->create(next_id++);
      for (size_t i = 0; i < n; ++i) {
        store->erase_random(rng);
        store->create(next_id++);
      }
      live = meter.current();
      peak = meter.peak();
    }
    benchmark::DoNotOptimize(store->size());
  }
  state.counters["peak_bytes"] = static_cast<double>(peak);
  state.counters["peak_B_per_entity"] = static_cast<double>(peak) / static_cast<double>(n);
  state.counters["live_B_per_entity"] = static_cast<double>(live) / static_cast<double>(n);
}

constexpr int64_t kChurnEntities = 1'000'000;
constexpr int64_t kIterateEntities = 100'000;

BENCHMARK(BM_Churn<ArenaStore>)->Arg(kChurnEntities)->Iterations(3)->UseManualTime()->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Churn<HashMapStore>)->Arg(kChurnEntities)->Iterations(3)->UseManualTime()->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Churn<LinkedNodeStore>)
    ->Arg(kChurnEntities)
    ->Iterations(3)
    ->UseManualTime()
    ->Unit(benchmark::kMillisecond);

BENCHMARK(BM_Iterate<ArenaStore>)->Arg(kIterateEntities)->UseManualTime()->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_Iterate<HashMapStore>)->Arg(kIterateEntities)->UseManualTime()->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_Iterate<LinkedNodeStore>)->Arg(kIterateEntities)->UseManualTime()->Unit(benchmark::kMicrosecond);

BENCHMARK(BM_Memory<ArenaStore>)->Arg(kChurnEntities)->Iterations(1)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Memory<HashMapStore>)->Arg(kChurnEntities)->Iterations(1)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Memory<LinkedNodeStore>)->Arg(kChurnEntities)->Iterations(1)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace flatslam

int main(int argc, char** argv) {
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  std::printf("process peak RSS: %.1f MiB (ru_maxrss %ld KiB)\n", static_cast<double>(usage.ru_maxrss) / 1024.0,
              usage.ru_maxrss);
  return 0;
}
