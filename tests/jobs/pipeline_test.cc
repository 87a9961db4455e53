#include "jobs/pipeline.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <future>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include <gtest/gtest.h>
#include <tbb/info.h>
#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>

#include "core/error.h"

namespace flatslam {
namespace {

using namespace std::chrono_literals;

// Runs fn on its own thread; aborts the test binary instead of hanging if it takes over 30 s.
template <class Fn>
auto WithWatchdog(Fn fn) -> decltype(fn()) {
  std::packaged_task<decltype(fn())()> task(std::move(fn));
  auto result = task.get_future();
  std::thread runner(std::move(task));
  if (result.wait_for(30s) != std::future_status::ready) {
    std::fprintf(stderr, "watchdog: FramePipeline::run() did not return within 30 s\n");
    std::abort();
  }
  runner.join();
  return result.get();
}

void RaiseMax(std::atomic<int>& slot, int value) {
  int seen = slot.load();
  while (seen < value && !slot.compare_exchange_weak(seen, value)) {
  }
}

bool HasTwoThreads() {
  return tbb::info::default_concurrency() >= 2 && std::thread::hardware_concurrency() >= 2;
}

// Counts live items (moved-from shells excluded) so tests can bound memory.
struct LiveCounter {
  std::atomic<int> alive{0};
  std::atomic<int> max_alive{0};
};

struct Item {
  Item(size_t seq, LiveCounter* counter) : seq(seq), counter(counter) {
    if (counter != nullptr) RaiseMax(counter->max_alive, counter->alive.fetch_add(1) + 1);
  }
  Item(Item&& other) noexcept : seq(other.seq), counter(std::exchange(other.counter, nullptr)) {}
  Item& operator=(Item&&) = delete;
  ~Item() {
    if (counter != nullptr) counter->alive.fetch_sub(1);
  }

  size_t seq;
  LiveCounter* counter;
  int work = 0;
};

// Source of n items (n = 0 means endless).
FramePipeline<Item>::Source CountingSource(size_t n, LiveCounter* counter = nullptr) {
  return [n, counter](size_t seq) -> std::optional<Item> {
    if (n != 0 && seq >= n) return std::nullopt;
    return Item(seq, counter);
  };
}

// Deterministic per-item pseudo-random value, so parallel stages share no generator.
uint64_t Mix(uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

TEST(FramePipeline, PreservesOrderThroughRandomlySlowParallelStages) {
  constexpr size_t kItems = 2000;
  FramePipeline<Item> pipeline;
  std::vector<size_t> seen;
  pipeline.set_source(CountingSource(kItems))
      .add_parallel_stage("extract",
                          [](Item& item) {
                            std::this_thread::sleep_for(std::chrono::microseconds(Mix(item.seq) % 300));
                            item.work = 1;
                          })
      .add_parallel_stage("describe",
                          [](Item& item) {
                            std::this_thread::sleep_for(std::chrono::microseconds(Mix(item.seq + kItems) % 100));
                            item.work += 1;
                          })
      .add_serial_stage("track", [&seen](Item& item) {
        EXPECT_EQ(item.work, 2);
        seen.push_back(item.seq);
      });
  const PipelineStats stats = WithWatchdog([&] { return pipeline.run(); });
  EXPECT_EQ(stats.items_processed, kItems);
  ASSERT_EQ(seen.size(), kItems);
  for (size_t i = 0; i < kItems; ++i) ASSERT_EQ(seen[i], i) << "serial stage saw items out of order";
}

TEST(FramePipeline, SerialStagesRunInOrderPerItem) {
  FramePipeline<Item> pipeline;
  std::vector<std::pair<int, size_t>> calls;
  pipeline.set_source(CountingSource(50))
      .add_serial_stage("first", [&calls](Item& item) { calls.emplace_back(1, item.seq); })
      .add_serial_stage("second", [&calls](Item& item) { calls.emplace_back(2, item.seq); });
  WithWatchdog([&] { return pipeline.run(); });
  ASSERT_EQ(calls.size(), 100u);
  for (size_t i = 0; i < 50; ++i) {
    EXPECT_EQ(calls[2 * i], std::make_pair(1, i));
    EXPECT_EQ(calls[2 * i + 1], std::make_pair(2, i));
  }
}

TEST(FramePipeline, ParallelStageRunsConcurrently) {
  if (!HasTwoThreads()) GTEST_SKIP() << "needs at least two hardware threads";
  std::atomic<int> current{0};
  std::atomic<int> most{0};
  FramePipeline<Item> pipeline;
  pipeline.set_source(CountingSource(200)).add_parallel_stage("extract", [&](Item&) {
    RaiseMax(most, current.fetch_add(1) + 1);
    std::this_thread::sleep_for(2ms);
    current.fetch_sub(1);
  });
  WithWatchdog([&] { return pipeline.run(); });
  EXPECT_GT(most.load(), 1);
}

TEST(FramePipeline, ParallelStageConcurrencyLimitHolds) {
  std::atomic<int> current{0};
  std::atomic<int> most{0};
  FramePipeline<Item> pipeline;
  pipeline.set_source(CountingSource(100))
      .add_parallel_stage(
          "extract",
          [&](Item&) {
            RaiseMax(most, current.fetch_add(1) + 1);
            std::this_thread::sleep_for(200us);
            current.fetch_sub(1);
          },
          ParallelStageOptions{.concurrency = 1});
  WithWatchdog([&] { return pipeline.run(); });
  EXPECT_EQ(most.load(), 1);
}

TEST(FramePipeline, InFlightLimitBoundsLiveItems) {
  constexpr size_t kLimit = 3;
  LiveCounter counter;
  FramePipeline<Item> pipeline(PipelineOptions{.max_in_flight = kLimit});
  pipeline.set_source(CountingSource(300, &counter))
      .add_parallel_stage("extract", [](Item&) {})
      .add_serial_stage("track", [](Item&) { std::this_thread::sleep_for(200us); });
  const PipelineStats stats = WithWatchdog([&] { return pipeline.run(); });
  EXPECT_EQ(stats.items_processed, 300u);
  EXPECT_LE(counter.max_alive.load(), static_cast<int>(kLimit));
  EXPECT_LE(stats.max_in_flight_observed, kLimit);
  // With a second thread the source outruns the slow serial stage, so the limit is reached.
  if (HasTwoThreads()) {
    EXPECT_EQ(stats.max_in_flight_observed, kLimit);
  }
  EXPECT_EQ(counter.alive.load(), 0) << "items leaked";
}

TEST(FramePipeline, RejectsZeroInFlightLimit) {
  EXPECT_FALSE(PipelineOptions{.max_in_flight = 0}.Check());
  EXPECT_TRUE(PipelineOptions{}.Check());
  FramePipeline<Item> pipeline(PipelineOptions{.max_in_flight = 0});
  pipeline.set_source(CountingSource(10));
  EXPECT_THROW(pipeline.run(), Error);
}

TEST(FramePipeline, EmptySourceFinishes) {
  FramePipeline<Item> pipeline;
  size_t calls = 0;
  pipeline.set_source([](size_t) -> std::optional<Item> { return std::nullopt; }).add_serial_stage("track", [&](Item&) {
    ++calls;
  });
  const PipelineStats stats = WithWatchdog([&] { return pipeline.run(); });
  EXPECT_EQ(stats.items_processed, 0u);
  EXPECT_EQ(calls, 0u);
}

TEST(FramePipeline, CanRunAgain) {
  FramePipeline<Item> pipeline;
  std::vector<size_t> seen;
  pipeline.set_source(CountingSource(100)).add_serial_stage("track", [&](Item& item) { seen.push_back(item.seq); });
  EXPECT_EQ(WithWatchdog([&] { return pipeline.run(); }).items_processed, 100u);
  EXPECT_EQ(WithWatchdog([&] { return pipeline.run(); }).items_processed, 100u);
  ASSERT_EQ(seen.size(), 200u);
  EXPECT_EQ(seen[100], 0u);
  EXPECT_EQ(seen[199], 99u);
}

// Runs the pipeline expecting a PipelineError; checks stage, index and the nested original.
void ExpectFailure(FramePipeline<Item>& pipeline, const std::string& stage, size_t index, const std::string& text) {
  std::string error;
  WithWatchdog([&] {
    try {
      pipeline.run();
      error = "run() returned normally";
    } catch (const PipelineError& e) {
      EXPECT_EQ(e.stage(), stage);
      EXPECT_EQ(e.index(), index);
      EXPECT_NE(std::string(e.what()).find(text), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find(stage), std::string::npos) << e.what();
      try {
        std::rethrow_if_nested(e);
        error = "no nested exception";
      } catch (const std::runtime_error& original) {
        EXPECT_EQ(std::string(original.what()), text);
      }
    } catch (const std::exception& e) {
      error = std::string("unexpected exception type: ") + e.what();
    }
    return 0;
  });
  EXPECT_EQ(error, "");
}

TEST(FramePipeline, ParallelStageExceptionStopsRun) {
  LiveCounter counter;
  std::atomic<bool> armed{true};
  FramePipeline<Item> pipeline;
  pipeline
      .set_source(CountingSource(0, &counter))  // endless: only the failure ends the run
      .add_parallel_stage("extract",
                          [&](Item& item) {
                            if (armed.load() && item.seq == 500) throw std::runtime_error("extract exploded");
                          })
      .add_serial_stage("track", [](Item&) {});
  ExpectFailure(pipeline, "extract", 500, "extract exploded");
  EXPECT_EQ(counter.alive.load(), 0) << "items leaked after a failed run";

  // The pipeline is reusable after a failure.
  armed.store(false);
  pipeline.set_source(CountingSource(600, &counter));
  EXPECT_EQ(WithWatchdog([&] { return pipeline.run(); }).items_processed, 600u);
}

// A failure cancels the run, but a stage already running finishes its nested parallel work:
// cancelling it half way left extraction with half-built keypoints (a crash on a strict run).
TEST(FramePipeline, FailureDoesNotCutShortNestedParallelWork) {
  if (!HasTwoThreads()) GTEST_SKIP() << "needs two threads";
  std::atomic<bool> failed{false};
  std::atomic<int> done{0};
  FramePipeline<Item> pipeline;
  pipeline.set_source(CountingSource(2))
      .add_parallel_stage("extract",
                          [&](Item& item) {
                            if (item.seq == 1) {
                              failed.store(true);
                              throw std::runtime_error("item 1 failed");
                            }
                            // Item 0: start the nested work only once the run has been cancelled.
                            const auto until = std::chrono::steady_clock::now() + 2s;
                            while (!failed.load() && std::chrono::steady_clock::now() < until)
                              std::this_thread::yield();
                            std::this_thread::sleep_for(50ms);
                            tbb::parallel_for(0, 1000, [&](int) { done.fetch_add(1); });
                          })
      .add_serial_stage("track", [](Item&) {});
  ExpectFailure(pipeline, "extract", 1, "item 1 failed");
  EXPECT_EQ(done.load(), 1000);
}

TEST(FramePipeline, SerialStageExceptionStopsRun) {
  LiveCounter counter;
  FramePipeline<Item> pipeline;
  size_t last_seen = 0;
  pipeline.set_source(CountingSource(0, &counter))
      .add_parallel_stage("extract", [](Item&) {})
      .add_serial_stage("track",
                        [&](Item& item) {
                          if (item.seq == 100) throw std::runtime_error("track lost");
                          last_seen = item.seq;
                        })
      .add_serial_stage("after", [&](Item& item) { EXPECT_LT(item.seq, 100u); });
  ExpectFailure(pipeline, "track", 100, "track lost");
  EXPECT_EQ(last_seen, 99u);
  EXPECT_EQ(counter.alive.load(), 0);
}

TEST(FramePipeline, SourceExceptionStopsRun) {
  FramePipeline<Item> pipeline;
  size_t processed = 0;
  pipeline
      .set_source([](size_t seq) -> std::optional<Item> {
        if (seq == 50) throw std::runtime_error("camera unplugged");
        return Item(seq, nullptr);
      })
      .add_parallel_stage("extract", [](Item&) {})
      .add_serial_stage("track", [&](Item&) { ++processed; });
  ExpectFailure(pipeline, "source", 50, "camera unplugged");
  EXPECT_LE(processed, 50u);
}

TEST(FramePipeline, BackgroundJobExceptionStopsRun) {
  FramePipeline<Item> pipeline;
  auto mapping = pipeline.add_background_stage<int>("mapping", [](int& job) {
    if (job == 3) throw std::runtime_error("bundle adjustment diverged");
  });
  int next_job = 0;
  pipeline.set_source(CountingSource(0)).add_serial_stage("track", [&](Item&) { mapping.post(next_job++); });
  ExpectFailure(pipeline, "mapping", 3, "bundle adjustment diverged");
}

TEST(FramePipeline, BackgroundJobsRunInPostOrderAlongsideFrames) {
  if (!HasTwoThreads()) GTEST_SKIP() << "needs at least two hardware threads";
  constexpr size_t kItems = 400;
  std::atomic<size_t> tracked{0};
  std::atomic<size_t> progress_during_job{0};
  std::vector<size_t> done;  // written only by the serial background node
  FramePipeline<Item> pipeline;
  auto mapping = pipeline.add_background_stage<size_t>("mapping", [&](size_t& job) {
    if (job == 0) {
      // Holds the background node until frames have advanced past it, for up to 5 s: frames
      // that cannot run beside a job time out here, and a machine loaded by other work still
      // gives them the time they need.
      const size_t before = tracked.load();
      const auto deadline = std::chrono::steady_clock::now() + 5s;
      while (tracked.load() - before <= 10 && std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(1ms);
      progress_during_job.store(tracked.load() - before);
    } else {
      std::this_thread::sleep_for(std::chrono::microseconds(Mix(job) % 500));
    }
    done.push_back(job);
  });
  pipeline.set_source(CountingSource(kItems)).add_serial_stage("track", [&](Item& item) {
    if (item.seq % 10 == 0) mapping.post(item.seq);
    std::this_thread::sleep_for(500us);
    tracked.fetch_add(1);
  });
  const PipelineStats stats = WithWatchdog([&] { return pipeline.run(); });
  EXPECT_EQ(stats.items_processed, kItems);
  EXPECT_EQ(stats.background_jobs, kItems / 10);
  ASSERT_EQ(done.size(), kItems / 10) << "run() returned before the background queue drained";
  for (size_t i = 0; i < done.size(); ++i) EXPECT_EQ(done[i], 10 * i);
  EXPECT_GT(progress_during_job.load(), 10u) << "frames did not advance while a background job ran";
  EXPECT_EQ(mapping.depth(), 0u);
}

TEST(FramePipeline, BackgroundJobsDoNotStarveOnOneThread) {
  // Frame stages always have work here; jobs must still run between frames, not after the end.
  std::atomic<size_t> tracked{0};
  std::atomic<size_t> tracked_when_job_ran{0};
  std::atomic<bool> job_ran{false};
  FramePipeline<Item> pipeline;
  auto mapping = pipeline.add_background_stage<int>("mapping", [&](int&) {
    if (!job_ran.exchange(true)) tracked_when_job_ran.store(tracked.load());
  });
  pipeline
      .set_source([&](size_t seq) -> std::optional<Item> {
        if (job_ran.load() || seq >= 100000) return std::nullopt;
        return Item(seq, nullptr);
      })
      .add_parallel_stage("extract", [](Item&) {})
      .add_serial_stage("track", [&](Item& item) {
        if (item.seq == 0) mapping.post(0);
        tracked.fetch_add(1);
      });
  tbb::task_arena one_thread(1);
  WithWatchdog([&] { return one_thread.execute([&] { return pipeline.run(); }); });
  EXPECT_TRUE(job_ran.load());
  EXPECT_LT(tracked_when_job_ran.load(), 10u) << "the background job waited for the frames to run out";
}

TEST(FramePipeline, BoundedBackgroundQueueRefusesWithoutConsumingTheJob) {
  FramePipeline<Item> pipeline;
  std::atomic<size_t> ran{0};
  auto mapping = pipeline.add_background_stage<std::unique_ptr<int>>(
      "mapping",
      [&](std::unique_ptr<int>& job) {
        ASSERT_NE(job, nullptr);
        std::this_thread::sleep_for(2ms);
        ran.fetch_add(1);
      },
      BackgroundOptions{.capacity = 2});
  size_t accepted = 0;
  size_t refused = 0;
  size_t deepest = 0;
  // Three posts in a row: a job sleeps 2 ms, so the third finds the queue full on any machine.
  pipeline.set_source(CountingSource(50)).add_serial_stage("track", [&](Item& item) {
    for (int k = 0; k < 3; ++k) {
      auto job = std::make_unique<int>(static_cast<int>(item.seq));
      if (mapping.try_post(std::move(job))) {
        ++accepted;
      } else {
        ++refused;
        EXPECT_NE(job, nullptr) << "a refused job was moved from";
      }
      deepest = std::max(deepest, mapping.depth());
    }
  });
  const PipelineStats stats = WithWatchdog([&] { return pipeline.run(); });
  EXPECT_GE(refused, 50u);
  EXPECT_GE(accepted, 2u);
  EXPECT_EQ(accepted + refused, 150u);
  EXPECT_LE(deepest, 2u);
  EXPECT_LE(stats.max_background_depth, 2u);
  EXPECT_EQ(ran.load(), accepted);
}

TEST(FramePipeline, RunIsNotReentrant) {
  FramePipeline<Item> pipeline;
  pipeline.set_source(CountingSource(10)).add_serial_stage("track", [&](Item&) { pipeline.run(); });
  ExpectFailure(pipeline, "track", 0, "FramePipeline::run: already running");
}

TEST(FramePipeline, PostOutsideRunThrows) {
  FramePipeline<Item> pipeline;
  auto mapping = pipeline.add_background_stage<int>("mapping", [](int&) {});
  EXPECT_THROW(mapping.post(1), Error);
  EXPECT_EQ(mapping.depth(), 0u);
}

}  // namespace
}  // namespace flatslam
