#include "jobs/pipeline.h"

#include <algorithm>
#include <exception>
#include <functional>
#include <mutex>
#include <tuple>
#include <utility>
#include <vector>

#include <tbb/flow_graph.h>
#include <tbb/task_group.h>
#include <tbb/info.h>

namespace flatslam {

size_t DefaultMaxInFlight() {
  return 2 * static_cast<size_t>(std::max(1, tbb::info::default_concurrency()));
}

PipelineError::PipelineError(std::string stage, size_t index, const std::string& what)
    : Error(what), stage_(std::move(stage)), index_(index) {}

namespace pipeline_detail {
namespace {

namespace flow = tbb::flow;

// Permission for the source to create one item; the limiter counts tickets, not items.
struct Ticket {};

// One item on its way through the graph; the serial end frees the payload before releasing
// its ticket, so live items never outnumber tickets.
struct Envelope {
  size_t seq = 0;
  std::unique_ptr<Payload> payload;
};
using ItemMsg = std::shared_ptr<Envelope>;

struct JobEnvelope {
  std::unique_ptr<Payload> job;
};
using JobMsg = std::shared_ptr<JobEnvelope>;

// Raises `slot` to at least `value`.
void RaiseMax(std::atomic<size_t>& slot, size_t value) {
  size_t seen = slot.load();
  while (seen < value && !slot.compare_exchange_weak(seen, value)) {
  }
}

// Per-run bookkeeping shared by every node body; lives longer than the graph.
struct RunState {
  flow::graph* graph = nullptr;
  std::atomic<bool> failed{false};
  std::atomic<bool> source_done{false};
  size_t next_seq = 0;  // touched only by the serial produce node
  std::atomic<size_t> alive{0};
  std::atomic<size_t> max_alive{0};
  std::atomic<size_t> processed{0};
  std::atomic<size_t> jobs_done{0};

  std::mutex mutex;  // guards the first failure below
  std::exception_ptr error;
  std::string error_stage;
  size_t error_index = 0;
  bool error_in_job = false;

  // Records the first failure and cancels the graph; later failures are ignored.
  void Fail(const std::string& stage, size_t index, bool in_job, std::exception_ptr e) {
    {
      std::lock_guard<std::mutex> lock(mutex);
      if (!error) {
        error = std::move(e);
        error_stage = stage;
        error_index = index;
        error_in_job = in_job;
      }
    }
    failed.store(true);
    source_done.store(true);
    graph->cancel();
  }
};

// Jobs posted by the body running on this thread, handed to their queues when it returns (see
// RunIsolated); null outside a body.
thread_local std::vector<std::function<void()>>* t_deferred_posts = nullptr;

// Runs a stage body, the source or a job in a task-group context of its own. After a failure
// the graph is cancelled; without this, a body already running would see its nested parallel
// algorithms (extraction's parallel_invoke, the renderer's parallel_for) return with part of
// their work skipped and go on with it half done (a strict run crashed that way in extraction).
// Jobs the body posts reach their queue only when it returns: while it runs, its thread waits in
// the task group and may take any task spawned meanwhile; a job spawned there could run nested
// inside the body, and the stage (the serial track stage, say) would wait for the job to end.
// On a loaded machine that happened on most runs: no frame was tracked while mapping ran.
template <class F>
void RunIsolated(F&& body) {
  std::vector<std::function<void()>> deferred;
  std::vector<std::function<void()>>* const outer = std::exchange(t_deferred_posts, &deferred);
  struct Flush {
    std::vector<std::function<void()>>& posts;
    std::vector<std::function<void()>>* outer;
    ~Flush() {
      t_deferred_posts = outer;
      for (auto& post : posts) post();  // each job is run or, after a failure, skipped and counted off
    }
  } flush{deferred, outer};
  tbb::task_group_context context(tbb::task_group_context::isolated);
  tbb::task_group group(context);
  group.run_and_wait(std::forward<F>(body));
}

// Rethrows the recorded failure as PipelineError with the original nested inside.
[[noreturn]] void ThrowFailure(const RunState& state) {
  const auto message = [&](const std::string& cause) {
    return detail::Concat("pipeline stage '", state.error_stage, "' failed on ", state.error_in_job ? "job " : "item ",
                          state.error_index, ": ", cause);
  };
  try {
    std::rethrow_exception(state.error);
  } catch (const std::exception& e) {
    std::throw_with_nested(PipelineError(state.error_stage, state.error_index, message(e.what())));
  } catch (...) {
    std::throw_with_nested(PipelineError(state.error_stage, state.error_index, message("unknown exception")));
  }
}

}  // namespace

using JobNode = flow::function_node<JobMsg, flow::continue_msg>;
constexpr flow::node_priority_t kJobPriority = 1;  // above the frame nodes (no_priority)

// Where a queue's jobs go while a run is active.
struct QueueBinding {
  JobNode* node = nullptr;
};

bool QueueCore::Reserve() {
  size_t depth = depth_.load();
  do {
    if (options_.capacity != 0 && depth >= options_.capacity) return false;
  } while (!depth_.compare_exchange_weak(depth, depth + 1));
  NoteDepth(depth + 1);
  return true;
}

size_t QueueCore::ForceReserve() {
  const size_t depth = depth_.fetch_add(1) + 1;
  NoteDepth(depth);
  return depth;
}

void QueueCore::Unreserve() {
  depth_.fetch_sub(1);
}

void QueueCore::NoteDepth(size_t depth) {
  RaiseMax(max_depth_, depth);
}

void QueueCore::Submit(std::unique_ptr<Payload> job) {
  QueueBinding* binding = binding_.load(std::memory_order_acquire);
  if (binding == nullptr) {
    Unreserve();
    Fail("BackgroundQueue '", name_, "': post outside FramePipeline::run()");
  }
  auto message = std::make_shared<JobEnvelope>();
  message->job = std::move(job);
  // A queueing node always accepts. Inside a pipeline body the put waits for the body to end.
  if (t_deferred_posts != nullptr)
    t_deferred_posts->push_back([node = binding->node, message] { node->try_put(message); });
  else
    binding->node->try_put(message);
}

Core::Core(PipelineOptions options) : options_(options) {}

Core::~Core() = default;

void Core::CheckIdle(const char* what) const {
  FLATSLAM_CHECK(!running_.load(), "FramePipeline::", what, ": not allowed while run() is active");
}

void Core::SetSource(ErasedSource source) {
  CheckIdle("set_source");
  source_ = std::move(source);
}

void Core::AddParallel(std::string name, ErasedStage stage, ParallelStageOptions options) {
  CheckIdle("add_parallel_stage");
  FLATSLAM_CHECK(options.Check(), "FramePipeline: invalid options for parallel stage '", name, "'");
  parallel_.push_back(Stage{std::move(name), std::move(stage), options.concurrency});
}

void Core::AddSerial(std::string name, ErasedStage stage) {
  CheckIdle("add_serial_stage");
  serial_.push_back(Stage{std::move(name), std::move(stage), 1});
}

QueueCore& Core::AddBackground(std::string name, ErasedStage handler, BackgroundOptions options) {
  CheckIdle("add_background_stage");
  FLATSLAM_CHECK(options.Check(), "FramePipeline: invalid options for background stage '", name, "'");
  queues_.push_back(std::make_unique<QueueCore>(std::move(name), std::move(handler), options));
  return *queues_.back();
}

PipelineStats Core::Run() {
  FLATSLAM_CHECK(options_.Check(), "FramePipeline: max_in_flight must be > 0, got ", options_.max_in_flight);
  FLATSLAM_CHECK(source_ != nullptr, "FramePipeline::run: no source set");
  bool idle = false;
  FLATSLAM_CHECK(running_.compare_exchange_strong(idle, true), "FramePipeline::run: already running");
  struct Idle {
    std::atomic<bool>& running;
    ~Idle() { running.store(false); }
  } idle_on_exit{running_};

  for (auto& queue : queues_) {
    queue->depth_.store(0);
    queue->max_depth_.store(0);
  }

  RunState state;
  {
    flow::graph graph;  // declared before the nodes, so it is destroyed after them
    state.graph = &graph;

    flow::input_node<Ticket> tickets(graph, [&state](tbb::flow_control& control) -> Ticket {
      if (state.source_done.load()) control.stop();
      return {};
    });
    // Integral decrement: every put releases that many tickets, whatever the number of edges.
    flow::limiter_node<Ticket, long> limiter(graph, options_.max_in_flight);

    using ProduceNode = flow::multifunction_node<Ticket, std::tuple<ItemMsg, long>>;
    ProduceNode produce(graph, flow::serial, [this, &state](const Ticket&, ProduceNode::output_ports_type& ports) {
      if (!state.source_done.load()) {
        const size_t seq = state.next_seq;
        std::unique_ptr<Payload> payload;
        try {
          RunIsolated([&] { payload = source_(seq); });
        } catch (...) {
          state.Fail("source", seq, false, std::current_exception());
        }
        if (payload != nullptr) {
          ++state.next_seq;
          RaiseMax(state.max_alive, state.alive.fetch_add(1) + 1);
          auto message = std::make_shared<Envelope>();
          message->seq = seq;
          message->payload = std::move(payload);
          std::get<0>(ports).try_put(message);
          return;
        }
        state.source_done.store(true);
      }
      std::get<1>(ports).try_put(1L);  // no item for this ticket: give it back
    });

    std::vector<std::unique_ptr<flow::function_node<ItemMsg, ItemMsg>>> parallel_nodes;
    for (const Stage& stage : parallel_) {
      const size_t concurrency = stage.concurrency == 0 ? size_t{flow::unlimited} : stage.concurrency;
      parallel_nodes.push_back(std::make_unique<flow::function_node<ItemMsg, ItemMsg>>(
          graph, concurrency, [&state, &stage](const ItemMsg& message) {
            if (!state.failed.load()) {
              try {
                RunIsolated([&] { stage.fn(*message->payload); });
              } catch (...) {
                state.Fail(stage.name, message->seq, false, std::current_exception());
              }
            }
            return message;
          }));
    }

    flow::sequencer_node<ItemMsg> sequencer(graph, [](const ItemMsg& message) { return message->seq; });

    flow::function_node<ItemMsg, long> finish(graph, flow::serial, [this, &state](const ItemMsg& message) {
      for (const Stage& stage : serial_) {
        if (state.failed.load()) break;
        try {
          RunIsolated([&] { stage.fn(*message->payload); });
        } catch (...) {
          state.Fail(stage.name, message->seq, false, std::current_exception());
        }
      }
      message->payload.reset();  // the item dies before its ticket is released
      state.alive.fetch_sub(1);
      if (!state.failed.load()) state.processed.fetch_add(1);
      return 1L;
    });

    std::vector<std::unique_ptr<JobNode>> job_nodes;
    std::vector<QueueBinding> bindings(queues_.size());
    // Unbinds the queues before their nodes are destroyed, whatever happens below.
    struct Unbind {
      std::vector<std::unique_ptr<QueueCore>>& queues;
      ~Unbind() {
        for (auto& queue : queues) queue->binding_.store(nullptr, std::memory_order_release);
      }
    } unbind{queues_};
    std::vector<size_t> jobs_started(queues_.size(), 0);  // post index per queue; nodes are serial
    for (size_t q = 0; q < queues_.size(); ++q) {
      QueueCore* queue = queues_[q].get();
      size_t* counter = &jobs_started[q];
      // Priority makes TBB run job tasks as critical work between frame tasks, so a queue never
      // starves behind the frame stages' bypass chain (e.g. with one thread and an endless source).
      job_nodes.push_back(std::make_unique<JobNode>(
          graph, flow::serial,
          [&state, queue, counter](const JobMsg& message) {
            const size_t index = (*counter)++;
            if (!state.failed.load()) {
              try {
                RunIsolated([&] { queue->handler_(*message->job); });
              } catch (...) {
                state.Fail(queue->name_, index, true, std::current_exception());
              }
            }
            message->job.reset();
            queue->Unreserve();
            state.jobs_done.fetch_add(1);
            return flow::continue_msg();
          },
          flow::queueing(), kJobPriority));
      bindings[q].node = job_nodes.back().get();
      queue->binding_.store(&bindings[q], std::memory_order_release);
    }

    flow::make_edge(tickets, limiter);
    flow::make_edge(limiter, produce);
    flow::make_edge(flow::output_port<1>(produce), limiter.decrementer());
    if (parallel_nodes.empty()) {
      flow::make_edge(flow::output_port<0>(produce), sequencer);
    } else {
      flow::make_edge(flow::output_port<0>(produce), *parallel_nodes.front());
      for (size_t i = 1; i < parallel_nodes.size(); ++i) flow::make_edge(*parallel_nodes[i - 1], *parallel_nodes[i]);
      flow::make_edge(*parallel_nodes.back(), sequencer);
    }
    flow::make_edge(sequencer, finish);
    flow::make_edge(finish, limiter.decrementer());

    tickets.activate();
    try {
      graph.wait_for_all();
    } catch (...) {  // only TBB internals can throw here: bodies catch their own exceptions
      state.Fail("runtime", state.next_seq, false, std::current_exception());
    }
    if (graph.is_cancelled() && !state.failed.load()) {  // e.g. an enclosing task group was cancelled
      state.Fail("runtime", state.next_seq, false,
                 std::make_exception_ptr(Error("run cancelled from outside the pipeline")));
    }
  }

  PipelineStats stats;
  stats.items_processed = state.processed.load();
  stats.max_in_flight_observed = state.max_alive.load();
  stats.background_jobs = state.jobs_done.load();
  for (auto& queue : queues_) {
    stats.max_background_depth = std::max(stats.max_background_depth, queue->max_depth_.load());
    queue->depth_.store(0);  // jobs dropped by a failed run no longer count
  }
  if (state.error) ThrowFailure(state);
  return stats;
}

}  // namespace pipeline_detail
}  // namespace flatslam
