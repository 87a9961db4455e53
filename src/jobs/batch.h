// Many sequences in one process: each runs as RunSequence on its own calling thread, all sharing
// the process's TBB workers (one arena) and one memory-mapped vocabulary. How many run at once is
// bounded by a job count and a memory budget, so a batch never swaps.
// Concurrency: RunBatch blocks its caller; callbacks come from the caller's thread (progress,
// finished) or a sequence's track stage (warnings), never two at a time for one sequence.
#pragma once

#include <atomic>
#include <cstddef>
#include <filesystem>
#include <functional>
#include <string>
#include <vector>

#include "io/manifest.h"
#include "report/results.h"

namespace flatslam {

class Vocabulary;

struct SequenceProgress {
  std::string name;
  std::string state;     // queued, running, or the finished status (ok, failed, interrupted)
  std::string tracking;  // while running: the last frame's tracking state (tracking, lost, ...)
  size_t frames_done = 0, frames_total = 0;
  double fps = 0;  // frames done / seconds running
};

struct BatchProgress {
  std::vector<SequenceProgress> sequences;  // in input order
  size_t running = 0, finished = 0;
  size_t frames_done = 0, frames_total = 0;  // totals over the sequences opened so far
  double elapsed_s = 0;
  double eta_s = -1;  // from the frame rate so far; -1 while unknown
  double rss_mib = 0, budget_mib = 0;
};

struct BatchOptions {
  size_t jobs = 0;        // sequences at once; 0 = twice the number of cores (see batch.cc)
  double memory_mib = 0;  // resident-set budget; 0 = 80% of the memory available at the start
  const Vocabulary* vocabulary = nullptr;
  bool deterministic = false;
  std::filesystem::path out_dir;            // each sequence writes DIR/<name>/
  const std::atomic<bool>* stop = nullptr;  // set: no sequence starts, running ones stop early
  double progress_interval_s = 0.5;
  std::function<void(const BatchProgress&)> on_progress;  // every interval and once at the end
  std::function<void(const SequenceResult&)> on_finished;
  std::function<void(const std::string& sequence, const std::string& message)> on_warning;
};

// The admission rule of the memory budget, a pure function so it can be tested. A sequence is
// started when nothing runs, or when both the resident set now and the projection from the
// start (baseline plus one estimate per running sequence and the new one) fit the budget.
[[nodiscard]] bool AdmitSequence(size_t running, double rss_now_mib, double baseline_mib, double estimate_mib,
                                 double budget_mib);

// Runs every sequence; results in the order of `specs`, with SequenceResult::input set from
// `inputs` (their positions in the full input list; a shard passes its own). A sequence that
// fails is reported in its row and the batch goes on.
[[nodiscard]] std::vector<SequenceResult> RunBatch(const std::vector<SequenceSpec>& specs,
                                                   const std::vector<size_t>& inputs, const BatchOptions& options);

}  // namespace flatslam
