#include "jobs/batch.h"

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <fstream>
#include <memory>
#include <mutex>
#include <thread>

#include "jobs/sequence_run.h"

namespace flatslam {
namespace {

// What a sequence is assumed to need until one has finished and been measured: the resident-set
// growth of the largest shared snippet run alone (KITTI 06 stereo, 1241x376, 2000 features per
// image: about 200 MiB above the process's baseline), with headroom.
constexpr double kPriorSequenceMiB = 256;

// MemAvailable from /proc/meminfo in MiB (0 when unknown).
double AvailableMemoryMiB() {
  std::ifstream meminfo("/proc/meminfo");
  std::string key;
  double kib = 0;
  std::string unit;
  while (meminfo >> key >> kib >> unit)
    if (key == "MemAvailable:") return kib / 1024.0;
  return 0;
}

using Clock = std::chrono::steady_clock;
double Seconds(Clock::duration d) {
  return std::chrono::duration<double>(d).count();
}

// One sequence's live state, written by its thread and read by the batch's.
struct Slot {
  std::atomic<size_t> frames_done{0}, frames_total{0};
  std::atomic<bool> finished{false};
  // The last frame's tracking state (TrackingState as an int; -1: skipped or none yet).
  std::atomic<int> tracking{-1};
  std::string state = "queued";  // owned by the batch thread
  Clock::time_point started;
  std::atomic<double> peak_rss_mib{0};  // sampled by the batch thread while it runs
  size_t most_running = 1;              // most sequences running at once while it ran
  double baseline_mib = 0;              // the resident set when it started
  SequenceResult result;
  std::thread thread;
};

}  // namespace

bool AdmitSequence(size_t running, double rss_now_mib, double baseline_mib, double estimate_mib, double budget_mib) {
  if (running == 0) return true;
  const double projected = baseline_mib + static_cast<double>(running + 1) * estimate_mib;
  return rss_now_mib + estimate_mib <= budget_mib && projected <= budget_mib;
}

std::vector<SequenceResult> RunBatch(const std::vector<SequenceSpec>& specs, const std::vector<size_t>& inputs,
                                     const BatchOptions& options) {
  // A sequence keeps about one core busy at best: tracking and local mapping are serial per
  // sequence, and waits between them leave gaps. Two sequences per core fill the gaps; more
  // only cost memory. The memory budget still bounds it.
  const size_t jobs = options.jobs > 0 ? options.jobs : 2 * std::max<size_t>(1, std::thread::hardware_concurrency());
  const double budget = options.memory_mib > 0 ? options.memory_mib : 0.8 * AvailableMemoryMiB();
  const double baseline = CurrentRssMiB();
  double estimate = kPriorSequenceMiB;
  bool measured = false;  // estimate comes from finished sequences

  std::vector<std::unique_ptr<Slot>> slots;
  for (size_t i = 0; i < specs.size(); ++i) slots.push_back(std::make_unique<Slot>());
  std::mutex warning_mutex;
  // A finishing sequence wakes the coordinator at once; otherwise it samples the resident set
  // every 50 ms (the peak each running sequence is charged with).
  std::mutex done_mutex;
  std::condition_variable done;
  size_t next = 0, running = 0, finished = 0;
  const Clock::time_point start = Clock::now();
  Clock::time_point last_progress = start - std::chrono::hours(1);

  auto progress = [&] {
    BatchProgress p;
    p.running = running;
    p.finished = finished;
    p.elapsed_s = Seconds(Clock::now() - start);
    p.rss_mib = CurrentRssMiB();
    p.budget_mib = budget;
    size_t unopened = 0;
    for (size_t i = 0; i < specs.size(); ++i) {
      const Slot& s = *slots[i];
      SequenceProgress q;
      q.name = specs[i].name;
      q.state = s.state;
      q.frames_done = s.frames_done.load();
      q.frames_total = s.frames_total.load();
      if (const int t = s.tracking.load(); s.state == "running")
        q.tracking =
            t < 0 ? (q.frames_done > 0 ? "skipped" : "opening") : TrackingStateName(static_cast<TrackingState>(t));
      if (s.state != "queued") {
        const double seconds = s.state == "running" ? Seconds(Clock::now() - s.started) : s.result.wall_s;
        q.fps = seconds > 0 ? static_cast<double>(q.frames_done) / seconds : 0;
      }
      if (q.frames_total == 0 && s.state != "failed") ++unopened;
      p.frames_done += q.frames_done;
      p.frames_total += q.frames_total;
      p.sequences.push_back(std::move(q));
    }
    // ETA: the frames left at the batch's frame rate so far; sequences not opened yet are
    // counted at the mean length of those that are.
    const size_t opened = specs.size() - unopened;
    if (p.frames_done > 0 && opened > 0) {
      const double frames_left = static_cast<double>(p.frames_total - p.frames_done) +
                                 static_cast<double>(unopened) * static_cast<double>(p.frames_total) / opened;
      p.eta_s = frames_left / (static_cast<double>(p.frames_done) / p.elapsed_s);
    }
    if (options.on_progress) options.on_progress(p);
  };

  auto launch = [&](size_t i) {
    Slot& s = *slots[i];
    s.state = "running";
    s.started = Clock::now();
    s.baseline_mib = CurrentRssMiB();
    s.peak_rss_mib = s.baseline_mib;
    ++running;
    s.thread = std::thread([&, i] {
      Slot& slot = *slots[i];
      SequenceRunOptions run;
      run.vocabulary = options.vocabulary;
      run.deterministic = options.deterministic;
      run.out_dir = options.out_dir / specs[i].name;
      run.input = i < inputs.size() ? inputs[i] : i;
      run.stop = options.stop;
      run.on_opened = [&slot](size_t frames) { slot.frames_total = frames; };
      run.on_frame = [&slot](const FrameReport& r) {
        slot.tracking = r.skipped ? -1 : static_cast<int>(r.state);
        ++slot.frames_done;
      };
      run.peak_rss_mib = [&slot] { return slot.peak_rss_mib.load(); };
      if (options.on_warning)
        run.on_warning = [&, name = specs[i].name](const std::string& message) {
          const std::lock_guard<std::mutex> lock(warning_mutex);
          options.on_warning(name, message);
        };
      slot.result = RunSequence(specs[i], run);
      {
        const std::lock_guard<std::mutex> lock(done_mutex);
        slot.finished = true;
      }
      done.notify_all();
    });
  };

  while (finished < specs.size()) {
    // Start what the job count and the memory budget allow, in input order.
    const bool stopping = options.stop && options.stop->load();
    while (!stopping && next < specs.size() && running < jobs &&
           AdmitSequence(running, CurrentRssMiB(), baseline, estimate, budget))
      launch(next++);
    if (stopping) {
      // Sequences not started are reported as interrupted, with no output but their row.
      for (; next < specs.size(); ++next) {
        Slot& s = *slots[next];
        s.state = s.result.status = "interrupted";
        s.result.name = specs[next].name;
        s.result.dataset = specs[next].dataset;
        s.result.input = next < inputs.size() ? inputs[next] : next;
        s.result.error = "not started: the batch was interrupted";
        ++finished;
        if (options.on_finished) options.on_finished(s.result);
      }
    }
    {
      std::unique_lock<std::mutex> lock(done_mutex);
      done.wait_for(lock, std::chrono::milliseconds(50), [&] {
        return std::any_of(slots.begin(), slots.end(),
                           [](const auto& slot) { return slot->state == "running" && slot->finished; });
      });
    }
    const double rss = CurrentRssMiB();
    for (auto& slot : slots) {
      Slot& s = *slot;
      if (s.state != "running") continue;
      s.peak_rss_mib = std::max(s.peak_rss_mib.load(), rss);
      s.most_running = std::max(s.most_running, running);
      if (!s.finished) continue;
      s.thread.join();
      s.state = s.result.status;
      --running;
      ++finished;
      // What this sequence took: its peak above the resident set it started with, shared among
      // the sequences that ran beside it. The largest seen is the estimate for the next.
      const double used = (s.peak_rss_mib.load() - s.baseline_mib) / static_cast<double>(s.most_running);
      if (s.result.status == "ok") {
        estimate = measured ? std::max(estimate, used) : std::max(used, 1.0);
        measured = true;
      }
      if (options.on_finished) options.on_finished(s.result);
    }
    if (Seconds(Clock::now() - last_progress) >= options.progress_interval_s) {
      last_progress = Clock::now();
      progress();
    }
  }
  progress();
  std::vector<SequenceResult> results;
  for (auto& s : slots) results.push_back(std::move(s->result));
  return results;
}

}  // namespace flatslam
