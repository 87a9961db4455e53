// A SLAM session: one map and the systems over it, for monocular, stereo and RGB-D input.
// Feature extraction (frontend) runs on many frames at once; tracking (tracking/tracker.h) reads
// the map frame by frame; local mapping (mapping/local_mapping.h) writes what tracking found and
// refines the map per keyframe; loop closing (place/loop_closing.h) indexes keyframes, corrects
// loops and hands global bundle adjustment to background work. Nothing is static: several
// sessions live side by side in one process.
// Concurrency: Extract() is const and runs on many frames at once; Track() is called from one
// serial lane (frames in order); MapKeyFrame() from one mapping lane; global bundle adjustment
// from the owner's background lane (SetBackground). Every step declares the components it reads
// and writes (Steps()) and holds that access from the session's AccessGuard while it runs:
// tracking excludes the map's writers for a whole frame; the triangulation search and the bundle
// adjustment solves run on copies with no access, so tracking goes on beside them.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "config/context.h"
#include "config/options.h"
#include "core/object_pool.h"
#include "ecs/access.h"
#include "ecs/chunk_log.h"
#include "ecs/map.h"
#include "frontend/frame.h"
#include "frontend/orb_extractor.h"
#include "io/types.h"
#include "mapping/local_mapping.h"
#include "place/keyframe_database.h"
#include "place/loop_closing.h"
#include "tracking/tracker.h"

namespace flatslam {

class SlamSession {
 public:
  // Every step the session runs, with its declared access and lane ("extract" on many frames at
  // once, "track" once per frame in order, "mapping" on the one mapping node, "background" and
  // "checkpoint" beside them). Steps that declare some access take it from the session's guard
  // while they run (guarded); steps that declare none touch no shared component.
  [[nodiscard]] static std::span<const AccessStep> Steps();

  // Throws flatslam::Error on invalid options or calibration.
  SlamSession(const Calibration& calibration, const SlamOptions& options);

  // Extracts features (left and right in parallel) and stereo/RGB-D depth into *out; keypoints
  // of a frame with a lens are moved through it (Frame::lens). A monocular frame's keypoints as
  // measured in its image, before the lens, go to *measured when it is not null.
  void Extract(const Frame& frame, TrackedFrame* out, Keypoints* measured = nullptr) const;
  // A monocular frame made from the keypoints an earlier Extract measured in the same image with
  // the same ORB options (its *measured), moved through frame.lens: Extract's result without
  // reading or extracting the image again. frame gives the index, time and lens only.
  void ExtractFrom(const Keypoints& measured, const Frame& frame, TrackedFrame* out) const;
  // Tracks the frame. When it becomes a keyframe, *new_keyframe is set: pass it to MapKeyFrame().
  FrameReport Track(TrackedFrame&& frame, std::optional<KeyFrameHandle>* new_keyframe);
  // Local mapping for one keyframe: point upkeep, triangulation, fusion, local BA, culling.
  void MapKeyFrame(KeyFrameHandle keyframe);

  // Estimated camera poses of all tracked frames (T_world_cam), refined by mapping through
  // their reference keyframes. Call when no stage is running.
  [[nodiscard]] Trajectory FrameTrajectory() const;
  [[nodiscard]] Trajectory KeyFrameTrajectory() const;
  // Direct map access when no stage is running.
  [[nodiscard]] const Map& map() const { return map_; }
  [[nodiscard]] const SystemContext& context() const { return context_; }
  [[nodiscard]] int pending_keyframes() const { return pending_keyframes_; }
  // Tracking wanted a keyframe on the last frame but local mapping was busy; local BA stops early
  // while it is set, and a batch run waits for mapping instead of tracking on.
  [[nodiscard]] bool keyframe_wanted() const { return keyframe_wanted_; }
  // Loop corrections and global bundle adjustments applied to the map so far: each moved keyframes
  // made long before (a map server's copy of them is stale after one). Any thread.
  [[nodiscard]] uint64_t map_corrections() const { return map_corrections_.load(); }
  // A global bundle adjustment after a loop runs in the background: the map will move again when
  // it ends (a correction). Any thread.
  [[nodiscard]] bool global_bundle_adjustment_running() const { return global_ba_running_.load(); }
  // Loop closures so far (call when no stage is running).
  [[nodiscard]] const std::vector<LoopClosure>& loop_closures() const { return loops_.closures; }
  [[nodiscard]] size_t database_size() const { return database_.size(); }
  // Local mapping's time per stage (call when no stage is running).
  [[nodiscard]] const MappingTimes& mapping_times() const { return mapping_.times; }
  // Where background work (global bundle adjustment after a loop) runs: `start` is handed each
  // task and must run it off the calling (mapping) thread, waiting first for the task it was
  // handed before; its owner (src/jobs) waits for the last one before the session ends. Unset:
  // tasks run inline, on the mapping thread. Set before the first frame.
  void SetBackground(std::function<void(std::function<void()>)> start) { background_ = std::move(start); }
  // Ends background work at once (an interrupted session): a running global bundle adjustment
  // stops at its next iteration and its result is dropped; none starts afterwards. The caller
  // then waits for the running task where it runs.
  void AbandonBackground() { abandon_background_ = true; }
  // Receives one line when background work fails and the session goes on without it (global
  // bundle adjustment, loop closing). Called on the failing thread; set before the first frame.
  // Unset: the line goes to stderr.
  void SetWarningSink(std::function<void(const std::string&)> sink) { warning_sink_ = std::move(sink); }
  // Forces tracking lost from the next frame on (tests and the --lose-at option).
  void ForceLost();
  // Continues a saved map (call before the first frame): its keyframes are indexed for place
  // recognition and tracking starts by relocalizing in it. Needs a vocabulary. A session on an
  // adopted map never starts a new map segment: it stays lost until it relocalizes. `frames` is the
  // trajectory of the session being continued (references are keyframes of `map`, or null):
  // FrameTrajectory() starts with them, and later corrections of the map move them too.
  // resume_tracking: the first frame given to Track follows the last of `frames` in the input (a
  // resumed checkpoint of the same dataset): tracking goes on from the last two frames' motion
  // (ResumeTracking) rather than relocalizing, and relocalizes only if that fails.
  void AdoptMap(Map&& map, std::span<const AnchoredFramePose> frames = {}, bool resume_tracking = false);
  // Runs a global bundle adjustment of the map as one after a loop runs (on the background lane,
  // no loop searched meanwhile): for an adopted checkpoint whose copy caught one running
  // (State::global_adjustment_pending), so that the resumed session does not lose it. Call after
  // AdoptMap, before the first frame.
  void StartGlobalBundleAdjustment();
  // A move of the map's frame (MoveMapFrame, X_new = move * X_old) after the first
  // `frames_before` frame records.
  struct FrameMoveRecord {
    size_t frames_before = 0;
    Similarity3 move;
  };
  // The session between two frames, for a checkpoint: a copy of the map (Map::AssignForSnapshot:
  // no bags of words), a view of every tracked frame's pose as recorded, the culled keyframes
  // those records may still name, and the frame after the last one tracked. Any thread; reads the
  // map while copying (its writers, tracking among them, wait meanwhile). Pass the same State each time: the
  // copy then moves little more than what changed since the last. The frame view reads the
  // session's own records: use a State only while its session lives.
  struct State {
    Map map;
    ChunkLog<AnchoredFramePose>::View frames;
    CulledKeyFrames culled;
    std::vector<FrameMoveRecord> moves;
    size_t next_frame = 0;  // input index after the last frame given to Track
    // A global bundle adjustment after a loop was running: `map` holds the loop's correction
    // without it (a session resumed from this copy runs it again: StartGlobalBundleAdjustment).
    bool global_adjustment_pending = false;
    // Every frame anchored at a keyframe of `map` (culled references followed to live ones; none
    // where no live keyframe is left), for a snapshot's session.
    void AnchoredToMap(std::vector<AnchoredFramePose>* out) const;
  };
  void CaptureState(State* out) const;
  // Calls read(map) while holding read access to the map (the "mapping.publish" step: a
  // keyframe's message for a map server, between two keyframes' mapping). Any thread.
  void ReadMap(const std::function<void(const Map&)>& read) const;
  // Moves the map into another world frame, X_new = scale * R X_old + t (T_new_old = [R|t]; a map
  // server's correction puts an agent's map in the merged map's frame): every keyframe and point;
  // tracked frames follow their reference keyframes, the tracker's last pose at the next frame, as
  // after a loop correction. A scale other than 1 is for monocular maps only (stereo and RGB-D
  // depths are metric; throws flatslam::Error): distances relative to keyframes (frame records,
  // the motion model, culled keyframes' links) scale with it.
  // Work computed on a copy of the map before the move (new points, local or global bundle
  // adjustment) is dropped. Frames tracked after it report map_frame one higher. The mapping
  // lane, between keyframes (the "mapping.move_frame" step).
  void MoveMapFrame(const Eigen::Isometry3d& T_new_old, double scale = 1.0);
  // After the last frame, with mapping drained and no global bundle adjustment running: edit(map)
  // rewrites the map in place (a monocular run's refined camera: every keypoint moved into it and
  // the map adjusted in it; RunSlam's end). Tracked frames follow their reference keyframes. The
  // session's context keeps the camera it tracked with, so it tracks no frame after this (Track
  // throws). The caller's thread (the "mapping.after_last_frame" step).
  void EditMapAfterLastFrame(const std::function<void(Map&)>& edit);

 private:
  static_assert(sizeof(AnchoredFramePose) == 72);

  // With the options already resolved for the calibration.
  SlamSession(const Calibration& calibration, SlamOptions&& resolved);

  // Writes what tracking asked for (sightings, keyframes) into the map (mapping system).
  InsertedTwoView ApplyTrackResult(TrackedFrame& frame, TrackResult& result);
  // The place node for one keyframe: bag of words into the index, loop detection and correction.
  void DetectAndCloseLoop(KeyFrameHandle keyframe);
  // Global bundle adjustment after the loops-th loop closure; dropped if another loop came meanwhile.
  void GlobalBundleAdjustment(size_t loops);
  // Hands GlobalBundleAdjustment(loops) to the background lane (inline without one); the caller
  // set global_ba_running_.
  void LaunchGlobalBundleAdjustment(size_t loops);
  void Warn(const std::string& message) const;

  OrbExtractor extractor_;
  mutable ObjectPool<ImagePyramid> pyramids_;  // Extract's work pyramids, reused across frames
  const SystemContext context_;

  // Each step takes the access it declares (Steps()) from access_; the members below are the
  // components it guards, named beside each.
  mutable AccessGuard access_;
  Map map_;                    // kMap (with map_corrected_ and map_epoch_)
  TrackerState tracker_;       // kTracker
  LocalMappingState mapping_;  // kLocalMapping; its buffers (snapshot, local BA) are the mapping node's own
  KeyFrameDatabase database_;  // kPlaceIndex
  LoopClosingState loops_;     // kLoops
  size_t next_frame_ = 0;      // kTrajectory: input index after the last frame tracked
  // One per tracked frame, for the trajectory. Fixed chunks that never move: no doubling's unused
  // half in a long session, and a checkpoint reads them through a view without copying. Older
  // chunks spill to a temporary file, so a session of any length holds two chunks in memory.
  ChunkLog<AnchoredFramePose> frame_poses_;
  bool map_corrected_ = false;  // a loop correction moved keyframes: refresh the last frame's pose
  bool frames_over_ = false;    // kMap: EditMapAfterLastFrame ran
  // Bumped whenever the whole map moves (loop correction, global BA): work computed on a copy
  // from an older epoch (local BA, new points) is dropped instead of written back.
  uint64_t map_epoch_ = 0;
  uint32_t map_frame_moves_ = 0;              // kMap: MoveMapFrame calls so far
  std::atomic<uint64_t> map_corrections_{0};  // loop corrections and global BAs applied so far
  std::vector<FrameMoveRecord> frame_moves_;  // kTrajectory: each move, after how many frame records
  // How the map moved after frame record i was written (moves: the session's or a State's).
  [[nodiscard]] static Similarity3 MovesSince(std::span<const FrameMoveRecord> moves, size_t i);

  // Between tracking and mapping, without the lock.
  std::atomic<int> pending_keyframes_{0};
  std::atomic<bool> keyframe_wanted_{false};
  std::function<void(std::function<void()>)> background_;
  std::atomic<bool> global_ba_running_{false};
  std::atomic<bool> abandon_background_{false};
  std::function<void(const std::string&)> warning_sink_;
};

}  // namespace flatslam
