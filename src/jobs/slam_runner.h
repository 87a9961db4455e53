// Runs the SLAM systems over a dataset on the frame pipeline: read + extract in parallel across
// frames, track in frame order, local mapping and checkpoint writes as background queues.
// Concurrency: RunSlam blocks the calling thread; it uses TBB workers for the stages. The
// callbacks below say which thread calls them.
#pragma once

#include <atomic>
#include <cstddef>
#include <functional>
#include <string>
#include <utility>
#include <vector>

#include "io/dataset.h"
#include "mapping/camera_check.h"
#include "mapping/rig_check.h"
#include "slam/session.h"

namespace flatslam {

struct SlamRunOptions {
  size_t max_frames = 0;       // 0 = every frame of the dataset; else frames [first_frame, max_frames)
  size_t first_frame = 0;      // frames before it are not read (a session continuing a saved map)
  Map* initial_map = nullptr;  // moved into the SLAM system before the first frame (SlamSession::AdoptMap)
  // With initial_map: the trajectory of the session it continues (a resumed checkpoint); the
  // result's trajectory starts with these frames.
  std::vector<AnchoredFramePose> initial_frames;
  // With initial_map: the checkpoint caught a global bundle adjustment running; it runs again
  // (SlamSession::StartGlobalBundleAdjustment).
  bool initial_global_adjustment = false;
  // Global bundle adjustment after a loop closure inline too (it otherwise runs beside tracking),
  // and every keyframe mapped in the track stage whatever the lag: same input, same output.
  bool deterministic = false;
  size_t max_in_flight = 0;  // frames read/extracted ahead of tracking; 0 = max(16, 4 x cores)
  // Tracking waits while more keyframes than this await local mapping, so a batch run, which
  // reads faster than real time, never tracks against a map that mapping has fallen behind on.
  // At 0 each keyframe is mapped in the track stage, as tracking would wait for it anyway.
  int max_mapping_lag = 0;
  // Frames [first, last) are never given to SLAM (dropped frames: the camera seems to jump).
  std::vector<std::pair<size_t, size_t>> skip;
  // Tracking is declared lost at these frames (relocalization tests).
  std::vector<size_t> lose_at;
  // Called from the track stage after every frame (progress display, streamed statistics); may
  // be empty.
  std::function<void(const FrameReport&)> on_frame;
  // Keep every frame's report in SlamRunResult::reports. A caller that consumes them in on_frame
  // can turn this off, so that a session of any length holds no per-frame record but its pose.
  bool keep_reports = true;
  // Called after each keyframe's local mapping, on the mapping lane (the track stage when mapping
  // runs inline), e.g. to publish it (SlamSession::ReadMap reads the map meanwhile) or to move the
  // map (SlamSession::MoveMapFrame); may be empty.
  std::function<void(SlamSession&, KeyFrameHandle)> on_keyframe_mapped;
  // Called once after every stage has drained, before RunSlam returns (e.g. to save the map);
  // may be empty.
  std::function<void(const SlamSession&)> on_finished;

  // A frame whose images cannot be read or do not fit the calibration (missing, unreadable,
  // truncated, wrong size or pixel type, a depth image unlike its colour image) is skipped like a
  // dropped frame: on_skipped hears why (track stage, in frame order), on_frame gets a report
  // with `skipped` set, and tracking goes on (relocalizing if it must). strict: the first such
  // frame ends the run with its error instead. A run where every frame is bad fails either way.
  bool strict = false;
  std::function<void(size_t index, const std::string& reason)> on_skipped;
  // When it becomes true (e.g. set by a signal handler) no further frame is read; frames already
  // read are tracked, local mapping finishes its queue, global BA is abandoned, and RunSlam
  // returns a result over the frames tracked (interrupted = true).
  const std::atomic<bool>* stop = nullptr;
  // Failures of background work the session survives (global BA, loop closing, checkpoint
  // writes), one line each; any thread. Unset: stderr.
  std::function<void(const std::string&)> on_warning;
  // Checkpoints: every checkpoint_every_s seconds (0 = never) the track stage copies the session
  // between two frames (SlamSession::CaptureState) and a background job hands the copy to on_checkpoint
  // with the first frame not yet tracked; the next copy is taken only once that one is written.
  // When the run ends (interrupted or not) a last one is written on the calling thread. A throw
  // from on_checkpoint becomes a warning; the session goes on.
  double checkpoint_every_s = 0;
  std::function<void(const SlamSession::State& state, size_t next_frame)> on_checkpoint;
  // When a stage or background job throws (strict mode's unreadable frame, a failed mapping step),
  // the run ends there: by default RunSlam rethrows; with keep_results_on_error it returns the
  // result over the frames tracked, with the message in SlamRunResult::error, so a caller can
  // still write what was computed.
  bool keep_results_on_error = false;
  // Called on the checkpoint job right before the copy, while the track stage is held between two
  // frames (so it may touch what on_frame writes): flush streamed outputs here, and they cover
  // every frame the checkpoint covers. May be empty.
  std::function<void()> before_checkpoint;
  // A monocular session's scale through turns follows small errors of the camera model
  // (mapping/camera_check.h). With check_camera, a monocular run without an initial map checks
  // the model against its own map early on (CameraCheckWindow); when the map disagrees with it
  // by an amount CameraCheckWindow::Refits accepts, the run starts over from its first frame
  // with the refined camera (each frame's keypoints undistorted by it: ApplyCameraRefit; its first
  // frames made from the keypoints the first pass measured), and checks that camera the same way
  // (a young map's refinement can fall short of the lens: what is left starts it over again, up
  // to CameraCheckWindow::kMaxRestarts times). Until a pass's check has decided, what on_frame
  // and on_skipped would hear is held back (and dropped if the run starts over) and no
  // checkpoint is written, so every output describes one run. Leave it off where keyframes leave
  // the process as they are made (a live agent).
  bool check_camera = false;
  // After the last frame, the pass that went on checks its whole map once more (once it holds the
  // window's next count of keyframes) and, when the map disagrees by what Refits accepts, moves
  // its keypoints into the refined camera and adjusts it there in place (no frame is tracked
  // again; a map's young part cannot tell what its whole motion can: a forward start, turns
  // later).
  // Called before each new start (restart = true), and when the end's check refines the camera
  // in place (false, before on_finished and the last checkpoint), with the refinement of the
  // dataset's camera (all so far, composed) and the calibration the map is then in.
  std::function<void(const CameraRefit&, const Calibration&, bool restart)> on_camera_refined;
  // With initial_map: the refinement of the dataset's own camera that `dataset` is already seen
  // through (the continued map's session made it), and that own camera (needed when refined:
  // without it the map's keypoints cannot move into another refinement, and the end's check is
  // skipped). A continued session never starts over; with check_camera it checks its whole map
  // after its last frame as above, composing onto continued_refit.
  CameraRefit continued_refit;
  PinholeCamera continued_given;
};

// When a run checks its camera: at keyframe counts growing by half from kFirst, while no more
// than kFrameShare of the run's frames are tracked and the map holds at most kMaxKeyFrames. The
// share bounds what starting over costs (at most about that share of the run again), the
// keyframe count and kMaxPoints each check's time (3-10 ms in the window, 0.05-1 s for a whole
// map after the last frame); neither is a property of a dataset. The corner shift has a floor,
// the keypoint noise at level 0 (a model change below it is not worth a second pass), and a
// ceiling, 5% of the image's half-diagonal: the check
// corrects what a calibration left over (KITTI 07's map asks for about 2%), not a camera it does
// not describe at all, and a young monocular map that is itself degenerate (a motorway seen by a
// short lens, whose scale collapses) can ask for absurd models (k1 = 3) at 5-10 standard errors.
// Such a check is reported and the given camera kept. A run starts over at most kMaxRestarts
// times (the last pass is not checked): each costs at most kFrameShare of the frames again. A pass
// that starts over makes its first kKeptFrames frames from the keypoints the first pass measured
// in the same images (about 15 MB held at 2000 features until the run goes on): only their lens
// differs, so they are neither read nor extracted again.
struct CameraCheckWindow {
  static constexpr size_t kFirst = 4;
  static constexpr double kFrameShare = 0.2;
  static constexpr size_t kMaxKeyFrames = 64;
  static constexpr size_t kMaxPoints = 3000;
  static constexpr double kMinCornerShiftPx = 1;
  static constexpr double kMaxCornerShiftShare = 0.05;
  static constexpr size_t kMaxRestarts = 2;
  static constexpr size_t kKeptFrames = 128;

  // The check disagrees with the camera by an amount the run corrects by starting over.
  [[nodiscard]] static bool Refits(const CameraCheck& check, const PinholeCamera& camera);
};

struct SlamRunResult {
  std::vector<FrameReport> reports;  // one per frame given to SLAM (see skip), in order; keep_reports
  size_t frames = 0;                 // frames given to SLAM
  Trajectory trajectory;             // tracked frames, T_world_cam, refined through keyframes
  Trajectory keyframes;
  size_t keyframe_count = 0, point_count = 0;
  std::vector<LoopClosure> loop_closures;
  MappingTimes mapping;  // local mapping's time per stage
  // Stereo: the rig's disparity offset as the final map measures it (mapping/rig_check.h).
  DisparityOffsetFit rig;
  double wall_s = 0;
  size_t frames_skipped = 0;  // unreadable frames (see SlamRunOptions::strict)
  bool interrupted = false;   // SlamRunOptions::stop ended the run
  std::string error;          // the error that ended the run early (keep_results_on_error)
  size_t next_frame = 0;      // first input frame not tracked (where a continuation starts)
  // Checkpoints written, and their cost to tracking: the copy, taken on the track stage, and the
  // tracking time of the frames tracked while a copy was taken or written (capture included).
  size_t checkpoints = 0, checkpoint_failures = 0;
  std::vector<double> checkpoint_capture_ms, checkpoint_write_ms;
  std::vector<double> frame_ms_during_checkpoints;
  // check_camera: the last check the run made (ok = false if none could say) and the camera it
  // checked (the given one, or a refined one after a restart); the refinement of the given camera
  // the run ended with (refined() false: it kept the given one), how many times it started over,
  // and the frames its earlier passes tracked before they did (those passes count in wall_s).
  CameraCheck camera_check;
  PinholeCamera camera_checked;
  CameraRefit camera_refit;
  size_t camera_restarts = 0;
  size_t frames_before_restart = 0;
  size_t frames_from_kept_keypoints = 0;  // of the pass that went on (CameraCheckWindow::kKeptFrames)
  // The camera the frames were tracked through, and its refinement of the given one (the
  // restarts'); the check of the whole map after the last frame (ok = false: none ran, or it
  // could not say), of that camera, and its time (the adjustment included; in wall_s). When it
  // refined the camera (camera_refit and calibration include that refinement): the keypoints
  // moved and the largest move.
  PinholeCamera camera_tracked;
  CameraRefit camera_refit_tracked;
  CameraCheck camera_check_at_end;
  double camera_end_ms = 0;
  bool camera_refined_at_end = false;
  size_t camera_end_keypoints = 0;
  double camera_end_max_shift_px = 0;
  Calibration calibration;  // the calibration the (last) session ran with
};

// Runs SLAM; the session is created from the dataset's calibration and options (and, with
// check_camera, may start over once with a refined camera).
[[nodiscard]] SlamRunResult RunSlam(const Dataset& dataset, const SlamOptions& options, const SlamRunOptions& run);

}  // namespace flatslam
