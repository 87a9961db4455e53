// flatslam server (in flatslam-live, see live.h): the map server that joins live agents' maps.
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <mutex>
#include <set>
#include <thread>

#include "agent_link.h"
#include "args.h"
#include "commands.h"
#include "core/error.h"
#include "merge/agent_maps.h"
#include "merge_and_save.h"
#include "net/dds.h"
#include "place/vocabulary.h"
#include "stop_signals.h"
#include "storage/keyframe_message.h"

namespace flatslam::app {

int RunServerLive(const std::vector<std::string>& argv) {
  const Args args(argv, {"out", "vocabulary", "dds-domain", "dds-peers", "agents", "idle"}, {});
  if (!args.positional().empty()) throw UsageError{"server takes no positional argument"};
  const auto out = args.get("out");
  if (!out) throw UsageError{"server needs --out DIR"};
  const std::filesystem::path out_dir(*out);
  std::filesystem::create_directories(out_dir);
  const int64_t agents_expected = args.get_int("agents", 0);
  const double idle_s = args.get_double("idle", 0);
  if ((agents_expected > 0) != (idle_s > 0)) throw UsageError{"--agents N and --idle S go together (both positive)"};
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
  std::printf("listening     %s on DDS domain %u (%s)\n", kKeyFrameTopic, dds.domain,
              dds.peers.empty() ? "multicast discovery" : "unicast discovery");
  std::fflush(stdout);

  const StopSignals stop_signals("flatslam server");
  AgentMaps maps;
  std::set<uint32_t> heard;
  size_t received = 0, dropped = 0, updates = 0;
  uint64_t bytes = 0;
  auto last = std::chrono::steady_clock::now();
  const auto start = last;
  while (!g_stop) {
    std::deque<Payload> batch;
    {
      std::unique_lock<std::mutex> lock(mutex);
      arrived.wait_for(lock, std::chrono::milliseconds(200), [&] { return !queue.empty(); });
      batch.swap(queue);
    }
    for (Payload& payload : batch) {
      ++received;
      bytes += payload.bytes.size();
      last = std::chrono::steady_clock::now();
      const std::string what =
          "keyframe message " + std::to_string(payload.sequence) + " from agent " + std::to_string(payload.agent);
      try {
        FLATSLAM_CHECK(payload.kind == PayloadKind::kKeyFrame, what, ": unknown kind ",
                       static_cast<uint32_t>(payload.kind));
        KeyFrameMessage message = DecodeKeyFrameMessage(payload.bytes, what);
        FLATSLAM_CHECK(message.agent == payload.agent, what, ": names agent ", message.agent, " inside");
        if (maps.camera()) {
          const Calibration& a = maps.camera()->calibration;
          const Calibration& b = message.camera.calibration;
          FLATSLAM_CHECK(a.camera.width == b.camera.width && a.camera.height == b.camera.height &&
                             a.camera.fx == b.camera.fx && a.sensor == b.sensor,
                         what, ": its camera differs from the first agent's (one server merges one camera model)");
        }
        heard.insert(message.agent);
        if (!maps.Add(std::move(message))) ++updates;
      } catch (const Error& e) {
        ++dropped;
        std::fprintf(stderr, "warning: dropped %s\n", e.what());
      }
    }
    const double idle = std::chrono::duration<double>(std::chrono::steady_clock::now() - last).count();
    if (agents_expected > 0 && static_cast<int64_t>(heard.size()) >= agents_expected && idle >= idle_s) break;
  }
  reader.reset();
  const double listen_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf(
      "received      %zu keyframe messages (%.1f MiB in %.1f s), %zu dropped as malformed, %zu updates of keyframes "
      "held\n",
      received, bytes / 1048576.0, listen_s, dropped, updates);
  for (const AgentMaps::Session& s : maps.sessions())
    std::printf("agent %-7u run %016llx: %zu keyframes, %zu map points\n", s.agent,
                static_cast<unsigned long long>(s.session), s.map.keyframes().size(), s.map.points().size());
  FLATSLAM_CHECK(maps.camera().has_value(), "no keyframe received on ", kKeyFrameTopic, " (DDS domain ", dds.domain,
                 "): no map written");

  SnapshotMetadata metadata;
  metadata.calibration = maps.camera()->calibration;
  metadata.scales = maps.camera()->scales;
  metadata.rgbd_virtual_baseline_m = maps.camera()->rgbd_virtual_baseline_m;
  metadata.vocabulary_checksum = vocabulary.checksum();
  MapMergeOptions options;
  options.bundle_adjustment.num_threads = static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  const MergeTimes times =
      MergeAndSave(maps.TakeMaps(vocabulary), vocabulary, metadata, options, out_dir / "map.fsmap");
  std::printf("time          merge %.0f ms, save %.0f ms\n", times.merge_ms, times.save_ms);
  if (g_signal != 0) return 128 + static_cast<int>(g_signal);
  return 0;
}

}  // namespace flatslam::app
