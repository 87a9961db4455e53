// flatslam server (in flatslam-live, see live.h): the map server that joins live agents' maps.
#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include "agent_link.h"
#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "jobs/background_worker.h"
#include "merge/agent_maps.h"
#include "merge/live_merge.h"
#include "merge_and_save.h"
#include "net/dds.h"
#include "place/vocabulary.h"
#include "stop_signals.h"
#include "storage/correction_message.h"
#include "storage/keyframe_message.h"

namespace flatslam::app {
namespace {

using Clock = std::chrono::steady_clock;

// An agent's correction is fitted on its newest keyframes: about the local map its tracking works
// in (ORB-SLAM's local window is the 10 to 20 keyframes sharing the most points with the current).
constexpr size_t kCorrectionKeyFrames = 10;

double Seconds(Clock::time_point from, Clock::time_point to) {
  return std::chrono::duration<double>(to - from).count();
}

// One merge of the maps as they were at `cut`, made while messages keep arriving.
struct LiveMerge {
  Clock::time_point cut, ready;
  Clock::time_point first_new;                      // the first message after the previous merge's cut
  std::vector<std::pair<uint32_t, uint64_t>> runs;  // agent, session of each input
  std::vector<std::vector<size_t>> members;         // inputs of each output map, first = its frame
  std::vector<std::optional<RunFrame>> frames;      // per input
  size_t keyframes = 0;
  // Of it: place recognition of the steps (the overlap graph's is the rest), append and fuse,
  // essential graph, weld bundle adjustments.
  double place_ms = 0, fuse_ms = 0, graph_ms = 0, weld_ms = 0;
  size_t loops = 0;  // closed in the merged maps, beyond the seams
  double loops_ms = 0;
  // Grown from the previous merge's maps (GrowingMerge) instead of merged again from the agents'.
  bool grown = false;
  GrowReport growth;
  size_t updates = 0;          // keyframes sent again between the previous merge's cut and this one's
  size_t runs_apart = 0;       // grown: runs it could not grow (in no merged map with another)
  bool overlap_apart = false;  // grown: one of them overlaps a merged map or another of them
  size_t apart_queries = 0;    // grown: keyframes that queried in that search
  size_t apart_keyframes = 0;  // grown: keyframes of the runs apart
  double apart_ms = 0;
};

SnapshotMetadata MetadataOf(const AgentCamera& camera, const Vocabulary& vocabulary) {
  SnapshotMetadata metadata;
  metadata.calibration = camera.calibration;
  metadata.scales = camera.scales;
  metadata.rgbd_virtual_baseline_m = camera.rgbd_virtual_baseline_m;
  metadata.vocabulary_checksum = vocabulary.checksum();
  return metadata;
}

// What fitting corrections after a merge needs of its inputs: each one's agent and keyframe poses.
struct MergeInputs {
  std::vector<uint32_t> agents;
  std::vector<KeyFramePoses> poses;
};

MergeInputs InputsOf(const AgentMaps::RunMaps& maps, LiveMerge* job) {
  MergeInputs inputs;
  job->runs = maps.runs;
  for (size_t i = 0; i < maps.maps.size(); ++i) {
    inputs.agents.push_back(maps.runs[i].first);
    inputs.poses.push_back(PosesOf(maps.maps[i]));
    job->keyframes += maps.maps[i].keyframes().size();
  }
  return inputs;
}

// The report of a growth of the kept merged maps by the messages since the last merge.
void RecordGrowth(const GrowingMerge& growing, GrowReport growth, LiveMerge* job) {
  job->grown = true;
  job->runs = growing.runs();
  job->members = growing.merged().members;
  job->frames = growing.frames();
  job->keyframes = growing.keyframes();
  job->loops = growth.loops.size();
  job->loops_ms = growth.loops_ms;
  job->weld_ms = growth.weld_ms;
  job->growth = growth;
  job->ready = Clock::now();
}

// The report of a full merge; `frames`: each input's frame in its output map (FitRunFrames).
void Record(const MultiMapMerge& merged, std::vector<std::optional<RunFrame>> frames, LiveMerge* job) {
  job->members = merged.members;
  for (const MergeAttempt& a : merged.attempts) {
    job->place_ms += a.report.place_ms;
    job->fuse_ms += a.report.fuse_ms;
    job->graph_ms += a.report.graph_ms;
    job->weld_ms += a.report.weld_ms;
  }
  for (const MergedMapLoops& l : merged.loops) {
    job->loops += l.closures.size();
    job->loops_ms += l.ms;
  }
  job->frames = std::move(frames);
  job->ready = Clock::now();
}

std::string RunName(const std::pair<uint32_t, uint64_t>& run) {
  char name[64];
  std::snprintf(name, sizeof(name), "agent %u run %016llx", run.first, static_cast<unsigned long long>(run.second));
  return name;
}

}  // namespace

int RunServerLive(const std::vector<std::string>& argv) {
  const Args args(argv, {"out", "vocabulary", "dds-domain", "dds-peers", "agents", "idle", "live-merge"}, {});
  if (!args.positional().empty()) throw UsageError{"server takes no positional argument"};
  const auto out = args.get("out");
  if (!out) throw UsageError{"server needs --out DIR"};
  const std::filesystem::path out_dir(*out);
  std::filesystem::create_directories(out_dir);
  const int64_t agents_expected = args.get_int("agents", 0);
  if (agents_expected < 0) throw UsageError{"--agents N: how many agents to wait for (positive)"};
  const double idle_s = args.get_double("idle", 0);
  if (!(idle_s >= 0)) throw UsageError{"--idle S: seconds of silence (positive)"};
  if (idle_s > 0 && agents_expected == 0) throw UsageError{"--idle S needs --agents N"};
  const double live_merge_s = args.get_double("live-merge", 2);
  if (!(live_merge_s >= 0)) throw UsageError{"--live-merge: seconds between live merges (0: none)"};
  const std::filesystem::path vocabulary_path =
      args.get("vocabulary") ? std::filesystem::path(*args.get("vocabulary")) : DefaultVocabularyPath();
  const Vocabulary vocabulary = Vocabulary::Load(vocabulary_path);
  const DdsOptions dds = ParseDdsOptions(args.get_or("dds-domain", "0"), args.get_or("dds-peers", "127.0.0.1"));

  // Samples arrive on the DDS listener thread; the main thread decodes and applies them.
  std::mutex mutex;
  std::condition_variable arrived;
  std::deque<Payload> queue;
  DdsNode node(dds, "flatslam server");
  auto reader = node.PayloadReader(kKeyFrameTopic, [&](const Payload& payload) {
    {
      const std::lock_guard<std::mutex> lock(mutex);
      queue.push_back(payload);
    }
    arrived.notify_one();
  });
  auto corrections = node.PayloadWriter(kCorrectionTopic);
  std::printf("listening     %s on DDS domain %u (%s)\n", kKeyFrameTopic, dds.domain,
              dds.peers.empty() ? "multicast discovery" : "unicast discovery");
  std::fflush(stdout);

  const StopSignals stop_signals("flatslam server");
  const auto start = Clock::now();
  AgentMaps maps;
  MapMergeOptions merge_options;
  // The merged map is the only place where loops across agents can close.
  merge_options.close_loops = true;
  merge_options.bundle_adjustment.num_threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  // Live merges leave the other cores to the receive loop (and, on one machine, to the agents).
  MapMergeOptions live_options = merge_options;
  live_options.bundle_adjustment.num_threads = 1;
  live_options.bundle_adjustment.schur_lm_threads = 1;
  // A global bundle adjustment after a loop in the merged map costs time in proportion to the
  // whole map, on the merge thread beside the agents; the final merge, from the agents' maps, runs it.
  live_options.adjust_after_loops = false;
  live_options.adjust_iterations = 0;  // likewise the adjustment of a merged map as a whole
  BackgroundWorker merger;
  std::mutex merged_mutex;
  std::optional<LiveMerge> merged_result;  // handed from the merge thread
  // The last live merge's maps, grown by later messages; used by one merge job at a time, and read
  // by the receive loop only while no job runs.
  std::unique_ptr<GrowingMerge> growing;
  std::vector<KeyFrameMessage> since_cut;                // keyframe messages applied since the last merge began
  size_t updates_since_cut = 0;                          // of them, keyframes the maps held already
  std::set<std::pair<uint32_t, uint64_t>> updated_runs;  // whose those were
  bool may_grow = false;                                 // a merge runs, or left maps to grow: keep since_cut
  bool overlap_seen = false;                             // a grown merge found runs apart overlapping: merge in full
  bool run_dropped = false;  // a resumed run replaced one: the kept maps hold it, merge in full
  bool merging = false;
  uint64_t revision = 0;
  size_t merged_messages = 0;  // messages held by the maps the last merge started from
  double last_merge_s = 0;
  Clock::time_point last_merge_end{}, previous_cut{}, first_after_cut{};
  std::set<std::pair<size_t, size_t>> together;  // run index pairs (by `runs_seen`) in one map
  std::vector<std::pair<uint32_t, uint64_t>> runs_seen;
  auto run_index = [&](const std::pair<uint32_t, uint64_t>& run) {
    const auto it = std::find(runs_seen.begin(), runs_seen.end(), run);
    if (it != runs_seen.end()) return static_cast<size_t>(it - runs_seen.begin());
    runs_seen.push_back(run);
    return runs_seen.size() - 1;
  };
  // A finished live merge: which runs met since the last one, and each run's correction.
  auto take_merge = [&](LiveMerge& m, const char* what) {
    ++revision;
    size_t joined_maps = 0;
    for (const auto& group : m.members) joined_maps += group.size() > 1;
    if (m.grown) {
      const GrowReport& g = m.growth;
      std::printf(
          "%s %-3llu grown at %.1f s: %zu keyframes added (%zu placed by the points they see; %zu updates, %zu of runs "
          "in no merged map), %zu keyframes "
          "of %zu runs, %.0f ms (join %.0f, weld %.0f of %zu keyframes, %zu loops closed in %.0f, fit %.0f)\n",
          what, static_cast<unsigned long long>(revision), Seconds(start, m.cut), g.added, g.placed_by_points,
          g.updated, g.skipped, m.keyframes, m.runs.size(), 1000 * Seconds(m.cut, m.ready), g.join_ms, g.weld_ms,
          g.welded_keyframes, m.loops, m.loops_ms, g.fit_ms);
      if (m.runs_apart > 0)
        std::printf("              %zu run(s) apart (%zu keyframes): %s (%zu keyframes queried, %.0f ms)\n",
                    m.runs_apart, m.apart_keyframes,
                    m.overlap_apart ? "one overlaps, the next merge joins it" : "no overlap yet", m.apart_queries,
                    m.apart_ms);
      for (const LoopClosure& c : g.loops)
        std::printf(
            "              loop: agent %u keyframe at %.2f s to agent %u's at %.2f s: %d points, moved %.3f m\n",
            c.agent, c.t_ns * 1e-9, c.matched_agent, c.matched_t_ns * 1e-9, c.matches, c.correction_m);
    } else {
      std::printf(
          "%s %-3llu maps at %.1f s: %zu keyframes of %zu runs (%zu sent again), %zu merged map(s), %zu alone, "
          "%.0f ms "
          "(merge steps: place recognition %.0f, fuse %.0f, essential graph %.0f, weld %.0f; %zu loops closed in "
          "%.0f)\n",
          what, static_cast<unsigned long long>(revision), Seconds(start, m.cut), m.keyframes, m.runs.size(), m.updates,
          joined_maps, m.members.size() - joined_maps, 1000 * Seconds(m.cut, m.ready), m.place_ms, m.fuse_ms,
          m.graph_ms, m.weld_ms, m.loops, m.loops_ms);
    }
    for (const auto& group : m.members) {
      for (size_t a = 0; a < group.size(); ++a) {
        for (size_t b = a + 1; b < group.size(); ++b) {
          const size_t ra = run_index(m.runs[group[a]]), rb = run_index(m.runs[group[b]]);
          if (!together.insert({std::min(ra, rb), std::max(ra, rb)}).second) continue;
          // The overlap that joined them was not in the maps of the previous merge (that merge
          // kept them apart) and was in these: it came with a message between the two cuts.
          std::printf(
              "met           %s and %s: merged map ready %.1f s after their first overlap at most "
              "(%.1f s after this merge's cut)\n",
              RunName(m.runs[group[a]]).c_str(), RunName(m.runs[group[b]]).c_str(), Seconds(m.first_new, m.ready),
              Seconds(m.cut, m.ready));
        }
      }
    }
    for (size_t i = 0; i < m.runs.size(); ++i) {
      if (!m.frames[i]) continue;
      const RunFrame& f = *m.frames[i];
      CorrectionMessage c;
      c.revision = revision;
      c.agent = m.runs[i].first;
      c.session = m.runs[i].second;
      const auto& frame_run = m.runs[m.members[f.output].front()];
      c.frame_agent = frame_run.first;
      c.frame_session = frame_run.second;
      c.rotation = f.S_output_input.R;
      c.translation = f.S_output_input.t;
      c.scale = f.S_output_input.s;
      c.keyframes = static_cast<uint32_t>(f.keyframes);
      c.rms_m = f.rms;
      c.runs = static_cast<uint32_t>(m.members[f.output].size());
      Payload payload;
      payload.agent = c.agent;
      payload.kind = PayloadKind::kCorrection;
      payload.sequence = revision;
      payload.bytes = EncodeCorrectionMessage(c);
      if (!corrections->Write(payload))
        std::fprintf(stderr, "warning: could not publish the correction of %s\n", RunName(m.runs[i]).c_str());
    }
    std::fflush(stdout);
  };
  // Starts a merge while the receive loop goes on: a growth of the kept merged maps by the
  // messages since the last merge when every run is in one of them with another run and those
  // messages only add keyframes, else a full merge of copies of the agents' maps as they are now.
  auto start_merge = [&](Clock::time_point now) {
    auto job = std::make_shared<LiveMerge>();
    job->cut = now;
    job->first_new = first_after_cut;
    std::vector<GrowingMerge::Run> runs;
    for (const AgentMaps::Session& session : maps.sessions()) runs.emplace_back(session.agent, session.session);
    std::vector<KeyFrameMessage> messages = std::move(since_cut);
    since_cut.clear();
    // A keyframe sent again (after the agent's loop correction, or its final update) moved in the
    // agent's map: the kept merged map's copy of it is stale, a full merge takes the new one. (A
    // run apart is not in the kept maps: its map is searched as it is now.)
    const std::vector<GrowingMerge::Run> updated(updated_runs.begin(), updated_runs.end());
    // Before any run has joined another there is nothing to grow: a full merge searches and joins
    // in one go.
    const bool grow = growing && growing->Uncovered(runs).size() < runs.size() &&
                      growing->Uncovered(updated).size() == updated.size() && !overlap_seen && !run_dropped;
    run_dropped = false;
    job->updates = updates_since_cut;
    updates_since_cut = 0;
    updated_runs.clear();
    overlap_seen = false;
    may_grow = true;
    AgentMaps::RunMaps copies;
    MergeInputs inputs;
    if (!grow) {
      copies = maps.CopyMaps(vocabulary);
      inputs = InputsOf(copies, job.get());
    } else if (const auto apart = growing->Uncovered(runs); !apart.empty()) {
      // Runs in no merged map with another (alone, or new): only their maps, to look for an overlap.
      copies = maps.CopyMaps(vocabulary, apart);
    }
    const SnapshotMetadata metadata = MetadataOf(*maps.camera(), vocabulary);
    const MergeCamera camera =
        MergeCamera::FromCalibration(metadata.calibration, metadata.scales, VirtualBaseline(metadata));
    {
      const std::lock_guard<std::mutex> lock(merged_mutex);
      merging = true;
    }
    merger.Start([&, job, camera, grow, inputs = std::move(inputs), copies = std::move(copies),
                  messages = std::move(messages)]() mutable {
      std::optional<LiveMerge> done;
      try {
        if (grow) {
          RecordGrowth(*growing, growing->Grow(messages, vocabulary), job.get());
          // A run apart that now overlaps: the next merge is a full one, which joins it.
          job->runs_apart = copies.runs.size();
          const auto search_start = Clock::now();
          const GrowingMerge::ApartSearch search = growing->SearchRunsApart(copies.runs, copies.maps, vocabulary);
          job->apart_ms = 1000 * Seconds(search_start, Clock::now());
          job->overlap_apart = search.found;
          job->apart_queries = search.queries;
          job->apart_keyframes = search.keyframes;
        } else {
          growing.reset();
          std::vector<RunSightings> sightings;
          for (size_t i = 0; i < copies.maps.size(); ++i)
            sightings.push_back(SightingsOf(copies.maps[i], copies.ids[i]));
          growing = std::make_unique<GrowingMerge>(
              MergeAllMaps(std::move(copies.maps), vocabulary, camera, live_options), copies.runs, sightings,
              inputs.poses, camera, live_options, kCorrectionKeyFrames);
          Record(growing->merged(), growing->frames(), job.get());
        }
        done = std::move(*job);
      } catch (const Error& e) {
        growing.reset();
        std::fprintf(stderr, "warning: live merge failed: %s\n", e.what());
      }
      {
        const std::lock_guard<std::mutex> lock(merged_mutex);
        merged_result = std::move(done);
        merging = false;
      }
      arrived.notify_one();
    });
  };
  std::set<uint32_t> heard;
  std::set<std::pair<uint32_t, uint64_t>> runs_heard;  // (agent, session) of every keyframe message so far
  // An agent has finished when its newest run (a restarted agent starts a new one) has ended.
  std::map<uint32_t, uint64_t> newest_run;
  std::set<std::pair<uint32_t, uint64_t>> ended;
  auto finished_agents = [&] {
    return std::count_if(newest_run.begin(), newest_run.end(), [&](const auto& run) { return ended.count(run) > 0; });
  };
  size_t received = 0, dropped = 0, updates = 0, culled = 0;
  uint64_t bytes = 0;
  auto last = start;
  while (!g_stop) {
    std::deque<Payload> batch;
    {
      std::unique_lock<std::mutex> lock(mutex);
      arrived.wait_for(lock, std::chrono::milliseconds(200), [&] { return !queue.empty(); });
      batch.swap(queue);
    }
    if (!batch.empty() && first_after_cut <= previous_cut) first_after_cut = Clock::now();
    for (Payload& payload : batch) {
      ++received;
      bytes += payload.bytes.size();
      last = Clock::now();
      const std::string what =
          "keyframe message " + std::to_string(payload.sequence) + " from agent " + std::to_string(payload.agent);
      try {
        if (payload.kind == PayloadKind::kCulled) {
          const KeyFramesCulled message = DecodeKeyFramesCulled(payload.bytes, what);
          FLATSLAM_CHECK(message.agent == payload.agent, what, ": names agent ", message.agent, " inside");
          culled += maps.Cull(message);
          continue;
        }
        if (payload.kind == PayloadKind::kRunEnded) {
          const RunEnded message = DecodeRunEnded(payload.bytes, what);
          FLATSLAM_CHECK(message.agent == payload.agent, what, ": names agent ", message.agent, " inside");
          heard.insert(message.agent);
          newest_run.try_emplace(message.agent, message.session);
          ended.insert({message.agent, message.session});
          if (message.resumed_by != 0) {
            // Killed, and resumed from its checkpoint by the run named: that run's map holds this
            // one's keyframes up to the checkpoint and sends them itself; the rest died with it.
            newest_run[message.agent] = message.resumed_by;
            const size_t held = maps.Drop(message.agent, message.session);
            run_dropped = true;
            std::printf(
                "resumed       %s continues as run %016llx from its checkpoint: its map here (%zu keyframes) "
                "dropped\n",
                RunName({message.agent, message.session}).c_str(), static_cast<unsigned long long>(message.resumed_by),
                held);
            std::fflush(stdout);
            continue;
          }
          size_t held = 0;
          for (const AgentMaps::Session& s : maps.sessions())
            if (s.agent == message.agent && s.session == message.session) held = s.map.keyframes().size();
          std::printf("ended         %s after %llu frames%s: %llu keyframes in its map, %zu held here\n",
                      RunName({message.agent, message.session}).c_str(),
                      static_cast<unsigned long long>(message.frames), message.stopped ? " (stopped)" : "",
                      static_cast<unsigned long long>(message.keyframes), held);
          std::fflush(stdout);
          continue;
        }
        FLATSLAM_CHECK(payload.kind == PayloadKind::kKeyFrame, what, ": unknown kind ",
                       static_cast<uint32_t>(payload.kind));
        KeyFrameMessage message = DecodeKeyFrameMessage(payload.bytes, what);
        FLATSLAM_CHECK(message.agent == payload.agent, what, ": names agent ", message.agent, " inside");
        newest_run[message.agent] = message.session;
        if (maps.camera()) {
          const Calibration& a = maps.camera()->calibration;
          const Calibration& b = message.camera.calibration;
          FLATSLAM_CHECK(a.camera.width == b.camera.width && a.camera.height == b.camera.height &&
                             a.camera.fx == b.camera.fx && a.sensor == b.sensor,
                         what, ": its camera differs from the first agent's (one server merges one camera model)");
        }
        heard.insert(message.agent);
        const std::pair<uint32_t, uint64_t> run{message.agent, message.session};
        if (runs_heard.insert(run).second) {
          std::printf("heard         %s: its first keyframe\n", RunName(run).c_str());
          std::fflush(stdout);
        }
        std::optional<KeyFrameMessage> kept;  // for the next merge, once the maps took it
        if (may_grow) kept = message;
        if (!maps.Add(std::move(message))) {
          ++updates;
          ++updates_since_cut;
          updated_runs.insert(run);
        }
        if (kept) since_cut.push_back(std::move(*kept));
      } catch (const Error& e) {
        ++dropped;
        std::fprintf(stderr, "warning: dropped %s\n", e.what());
      }
    }
    const auto now = Clock::now();
    std::optional<LiveMerge> finished;
    bool busy;
    {
      const std::lock_guard<std::mutex> lock(merged_mutex);
      finished.swap(merged_result);
      busy = merging;
    }
    // No merge runs: whether the next one could grow the kept maps (else the messages since its
    // cut are not needed, and a server whose maps never merge keeps none of them).
    if (!busy) may_grow = growing != nullptr;
    if (finished) {
      overlap_seen = finished->overlap_apart;
      last_merge_s = Seconds(finished->cut, finished->ready);
      last_merge_end = finished->ready;
      take_merge(*finished, "live merge");
    }
    // A live merge starts when keyframes arrived since the last one, at most every --live-merge
    // seconds and never sooner after one ends than it took: merging takes at most half a core.
    // A grown merge that found runs apart overlapping starts the full merge that joins them at once.
    if (live_merge_s > 0 && !busy && maps.sessions().size() >= 2 &&
        (overlap_seen || (received - dropped > merged_messages &&
                          Seconds(last_merge_end, now) >= std::max(live_merge_s, last_merge_s)))) {
      merged_messages = received - dropped;
      previous_cut = now;
      start_merge(now);
    }
    // With --agents N: every agent heard has ended its newest run, and there are N of them; or,
    // with --idle S, N agents were heard and none has sent anything for S seconds (an agent that
    // was killed never says it ended).
    const auto agents_heard = static_cast<int64_t>(heard.size());
    if (agents_expected > 0 && agents_heard >= agents_expected) {
      if (finished_agents() == agents_heard) {
        std::printf("finished      every agent's run ended (%lld agents)\n", static_cast<long long>(agents_heard));
        break;
      }
      if (idle_s > 0 && Seconds(last, now) >= idle_s) {
        std::printf("finished      %lld agents, nothing received for %.0f s (%lld of them ended their runs)\n",
                    static_cast<long long>(agents_heard), idle_s, static_cast<long long>(finished_agents()));
        break;
      }
    }
  }
  reader.reset();
  merger.Wait();
  if (merged_result) take_merge(*merged_result, "live merge");
  const double listen_s = Seconds(start, Clock::now());
  std::printf(
      "received      %zu messages on %s (%.1f MiB in %.1f s), %zu dropped as malformed, %zu updates of keyframes "
      "held, %zu keyframes removed as their agents culled them\n",
      received, kKeyFrameTopic, bytes / 1048576.0, listen_s, dropped, updates, culled);
  for (const AgentMaps::Session& s : maps.sessions())
    std::printf("agent %-7u run %016llx: %zu keyframes, %zu map points\n", s.agent,
                static_cast<unsigned long long>(s.session), s.map.keyframes().size(), s.map.points().size());
  FLATSLAM_CHECK(maps.camera().has_value(), "no keyframe received on ", kKeyFrameTopic, " (DDS domain ", dds.domain,
                 "): no map written");

  const SnapshotMetadata metadata = MetadataOf(*maps.camera(), vocabulary);
  const bool monocular = metadata.calibration.sensor == Sensor::kMonocular;
  // The final merge, of every keyframe: its corrections go out too (agents still running, and
  // any other subscriber, get them) before the server exits.
  LiveMerge final_merge;
  final_merge.cut = Clock::now();
  final_merge.first_new = first_after_cut;
  AgentMaps::RunMaps all = maps.TakeMaps(vocabulary);
  const MergeInputs inputs = InputsOf(all, &final_merge);
  const MergeTimes times =
      MergeAndSave(std::move(all.maps), vocabulary, metadata, merge_options, out_dir / "map.fsmap",
                   [&](const MultiMapMerge& merged) {
                     Record(merged, FitRunFrames(merged, inputs.agents, inputs.poses, !monocular, kCorrectionKeyFrames),
                            &final_merge);
                   });
  take_merge(final_merge, "final merge");
  if (!corrections->WaitForAcknowledgments(5))
    std::fprintf(stderr, "warning: not every subscriber acknowledged the final corrections within 5 s\n");
  std::printf("time          merge %.0f ms, save %.0f ms\n", times.merge_ms, times.save_ms);
  if (g_signal != 0) return 128 + static_cast<int>(g_signal);
  return 0;
}

}  // namespace flatslam::app
