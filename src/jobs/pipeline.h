// Frame pipeline runtime: ordered source -> parallel stages -> sequencer -> serial stages, plus
// serial background queues fed from the stages, run as one tbb::flow::graph. Holds no SLAM logic.
// Concurrency: configure and run() from one thread; stages run on TBB workers as documented below;
// BackgroundQueue::post/try_post/depth are thread-safe.
#pragma once

#include <atomic>
#include <cstddef>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "core/error.h"

namespace flatslam {

// Default bound on items in flight: twice TBB's default concurrency (at least 2).
[[nodiscard]] size_t DefaultMaxInFlight();

struct PipelineOptions {
  // Most items alive at once, counted from the source call that creates an item to the end of
  // its last serial stage; the source is not called while the bound is reached (back-pressure).
  size_t max_in_flight = DefaultMaxInFlight();  // default: 2 * TBB default concurrency

  [[nodiscard]] bool Check() const { return max_in_flight > 0; }
};

struct ParallelStageOptions {
  // Most items inside this stage at once; 0 = unlimited (bounded by max_in_flight anyway).
  size_t concurrency = 0;

  [[nodiscard]] bool Check() const { return true; }
};

struct BackgroundOptions {
  // try_post() refuses a job while this many are pending (posted, not finished); 0 = unbounded.
  // post() never blocks and never refuses: it returns the depth so the caller can throttle.
  size_t capacity = 0;

  [[nodiscard]] bool Check() const { return true; }
};

struct PipelineStats {
  size_t items_processed = 0;         // items that finished every serial stage
  size_t max_in_flight_observed = 0;  // most items alive at once (<= Options::max_in_flight)
  size_t background_jobs = 0;         // background jobs finished, all queues
  size_t max_background_depth = 0;    // most jobs pending in any one queue at once
};

// A stage, the source or a background job threw; the original exception is nested
// (std::rethrow_if_nested) and its message is part of what().
class PipelineError : public Error {
 public:
  PipelineError(std::string stage, size_t index, const std::string& what);
  // Name of the failing stage; "source" for the source.
  [[nodiscard]] const std::string& stage() const { return stage_; }
  // Item sequence number for the source and frame stages; post index for a background job.
  [[nodiscard]] size_t index() const { return index_; }

 private:
  std::string stage_;
  size_t index_;
};

namespace pipeline_detail {

// Type-erased value carried through the graph; FramePipeline<Item> boxes its Item in one.
struct Payload {
  virtual ~Payload() = default;
};

template <class T>
struct Boxed final : Payload {
  explicit Boxed(T&& v) : value(std::move(v)) {}
  T value;
};

using ErasedSource = std::function<std::unique_ptr<Payload>(size_t seq)>;  // nullptr ends
using ErasedStage = std::function<void(Payload&)>;

struct QueueBinding;  // the queue's flow node during run(); defined in pipeline.cc

// Type-erased background queue; owned by Core, addressed through BackgroundQueue<Job>.
class QueueCore {
 public:
  QueueCore(std::string name, ErasedStage handler, BackgroundOptions options)
      : name_(std::move(name)), handler_(std::move(handler)), options_(options) {}

  // Reserves a pending slot; false (nothing reserved) when the queue is at capacity.
  [[nodiscard]] bool Reserve();
  // Counts one more pending job regardless of capacity; returns the new depth.
  size_t ForceReserve();
  // Hands a job to the running graph; a slot must have been reserved. Throws outside run().
  void Submit(std::unique_ptr<Payload> job);
  void Unreserve();
  [[nodiscard]] size_t depth() const { return depth_.load(std::memory_order_relaxed); }
  [[nodiscard]] const std::string& name() const { return name_; }

 private:
  friend class Core;
  void NoteDepth(size_t depth);

  std::string name_;
  ErasedStage handler_;
  BackgroundOptions options_;
  std::atomic<size_t> depth_{0};
  std::atomic<size_t> max_depth_{0};
  std::atomic<QueueBinding*> binding_{nullptr};
};

// Type-erased runtime behind FramePipeline<Item>; all TBB code lives in pipeline.cc.
class Core {
 public:
  explicit Core(PipelineOptions options);
  ~Core();
  Core(const Core&) = delete;
  Core& operator=(const Core&) = delete;

  void SetSource(ErasedSource source);
  void AddParallel(std::string name, ErasedStage stage, ParallelStageOptions options);
  void AddSerial(std::string name, ErasedStage stage);
  QueueCore& AddBackground(std::string name, ErasedStage handler, BackgroundOptions options);
  PipelineStats Run();

 private:
  struct Stage {
    std::string name;
    ErasedStage fn;
    size_t concurrency = 0;
  };
  void CheckIdle(const char* what) const;

  PipelineOptions options_;
  ErasedSource source_;
  std::vector<Stage> parallel_;
  std::vector<Stage> serial_;
  std::vector<std::unique_ptr<QueueCore>> queues_;
  std::atomic<bool> running_{false};
};

}  // namespace pipeline_detail

// Handle to a background queue: jobs run one at a time, in post order, on a node of the running
// graph while frames keep flowing. Job tasks have scheduling priority over frame tasks, so a queue
// progresses even on a single thread. Valid as long as its FramePipeline; post only during run(),
// from a stage or a job (elsewhere it throws flatslam::Error).
template <class Job>
class BackgroundQueue {
  static_assert(std::is_move_constructible_v<Job>, "a background job must be movable");

 public:
  // Enqueues the job; never blocks, ignores capacity. Returns the pending depth including it.
  size_t post(Job job) {
    const size_t depth = core_->ForceReserve();
    Submit(std::move(job));
    return depth;
  }
  // Enqueues only below capacity; on false the job is not moved from and nothing is posted.
  [[nodiscard]] bool try_post(Job&& job) {
    if (!core_->Reserve()) return false;
    Submit(std::move(job));
    return true;
  }
  // Jobs posted and not finished (including one running).
  [[nodiscard]] size_t depth() const { return core_->depth(); }
  [[nodiscard]] const std::string& name() const { return core_->name(); }

 private:
  template <class Item>
  friend class FramePipeline;
  explicit BackgroundQueue(pipeline_detail::QueueCore* core) : core_(core) {}

  void Submit(Job&& job) {
    std::unique_ptr<pipeline_detail::Payload> box;
    try {
      box = std::make_unique<pipeline_detail::Boxed<Job>>(std::move(job));
    } catch (...) {
      core_->Unreserve();
      throw;
    }
    core_->Submit(std::move(box));
  }

  pipeline_detail::QueueCore* core_;
};

// Ordered frame pipeline over items of type Item (movable; e.g. a frame and its features):
//   source (serial, numbers items 0,1,2,...) -> parallel stages (each concurrent across items)
//   -> sequencer (restores source order) -> serial stages (in order, one item at a time).
// Each run() builds a fresh graph, so the pipeline is reusable: a later run() calls the source
// again from seq 0. run() is not reentrant (a concurrent second call throws flatslam::Error).
// On the first exception anywhere the run is cancelled, items and pending jobs are dropped, and
// run() throws PipelineError naming the stage and item. State captured by stages must outlive run().
template <class Item>
class FramePipeline {
  static_assert(std::is_move_constructible_v<Item>, "a pipeline item must be movable");

 public:
  // Called serially with seq = 0,1,2,... until it returns nullopt.
  using Source = std::function<std::optional<Item>(size_t seq)>;
  // Mutates one item; parallel stages must not share unsynchronized state across items.
  using Stage = std::function<void(Item&)>;

  explicit FramePipeline(PipelineOptions options = {}) : core_(options) {}

  FramePipeline& set_source(Source source) {
    FLATSLAM_CHECK(source != nullptr, "FramePipeline::set_source: empty function");
    core_.SetSource([source = std::move(source)](size_t seq) -> std::unique_ptr<pipeline_detail::Payload> {
      std::optional<Item> item = source(seq);
      if (!item) return nullptr;
      return std::make_unique<pipeline_detail::Boxed<Item>>(std::move(*item));
    });
    return *this;
  }

  // Appends a stage that runs on up to options.concurrency items at once, in any order.
  FramePipeline& add_parallel_stage(std::string name, Stage stage, ParallelStageOptions options = {}) {
    core_.AddParallel(name, Erase(name, std::move(stage)), options);
    return *this;
  }

  // Appends a stage that sees items in source order, one at a time, after every parallel stage.
  FramePipeline& add_serial_stage(std::string name, Stage stage) {
    core_.AddSerial(name, Erase(name, std::move(stage)));
    return *this;
  }

  // Adds a queue whose jobs `handler` processes serially in post order, concurrently with the
  // frame stages; run() returns only after every posted job finished.
  template <class Job>
  BackgroundQueue<Job> add_background_stage(std::string name, std::function<void(Job&)> handler,
                                            BackgroundOptions options = {}) {
    FLATSLAM_CHECK(handler != nullptr, "FramePipeline::add_background_stage '", name, "': empty function");
    pipeline_detail::QueueCore& queue = core_.AddBackground(
        std::move(name),
        [handler = std::move(handler)](pipeline_detail::Payload& p) {
          handler(static_cast<pipeline_detail::Boxed<Job>&>(p).value);
        },
        options);
    return BackgroundQueue<Job>(&queue);
  }

  // Runs until the source is exhausted, every item left the serial stages and every background
  // job finished; blocks the caller, which helps execute tasks. Throws PipelineError on failure.
  PipelineStats run() { return core_.Run(); }

 private:
  static pipeline_detail::ErasedStage Erase(const std::string& name, Stage stage) {
    FLATSLAM_CHECK(stage != nullptr, "FramePipeline: stage '", name, "' has an empty function");
    return [stage = std::move(stage)](pipeline_detail::Payload& p) {
      stage(static_cast<pipeline_detail::Boxed<Item>&>(p).value);
    };
  }

  pipeline_detail::Core core_;
};

}  // namespace flatslam
