// Map snapshots: atomic save of one or more maps to a flatbuffers file (schemas/map.fbs), a
// verified read-only view served in place from an mmap, and a bulk load into fresh Map arenas.
// Concurrency: free functions are reentrant (distinct files); a MapSnapshotView is immutable after
// construction and may be read from many threads.
#pragma once

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "core/mapped_file.h"
#include "ecs/map.h"
#include "io/calibration.h"
#include "trajectory/trajectory.h"

namespace flatslam {

namespace schema {
struct MapSnapshot;
struct MapSegment;
}  // namespace schema

// Format written by this build; files with a larger version are refused.
inline constexpr uint32_t kMapSnapshotFormatVersion = 1;
inline constexpr uint32_t kNoIndex = 0xffffffffu;  // "none" for an index in a snapshot

// Where a session stood when a checkpoint was taken, so that it can be resumed.
struct SnapshotSession {
  uint64_t next_frame = 0;             // first input frame not yet processed
  uint32_t map = 0;                    // position in the snapshot's maps of the session's map
  std::string dataset;                 // as given to flatslam run
  std::vector<std::string> arguments;  // the run's command line after "run"
  // The trajectory so far, in frame order; references are keyframes of that map (handles of the
  // saved map when saving, of the loaded one after LoadMapSnapshot).
  std::vector<AnchoredFramePose> frames;
  // The session's global bundle adjustment after a loop was running when it was copied (the map
  // holds the loop's correction without it): a resumed session runs it again.
  bool global_adjustment_pending = false;
};

// What a snapshot records besides the maps.
struct SnapshotMetadata {
  Calibration calibration;
  MapScales scales;
  uint64_t vocabulary_checksum = 0;        // identity of the vocabulary the map was built with; 0 = none
  std::optional<SnapshotSession> session;  // checkpoints only
  // RGB-D maps: the virtual stereo baseline of the keyframes' right_u (0 = not recorded).
  double rgbd_virtual_baseline_m = 0;
  // The camera a monocular session refined over the dataset's (calibration is the refined one).
  CameraRefit camera_refit;
  // Refined sessions: the camera as the dataset gave it, before camera_refit (fx 0: not recorded).
  PinholeCamera given_camera;
};

// One map to save. Its agents are the distinct KeyFrame::agent values.
struct SnapshotMapRef {
  uint32_t id = 0;
  const Map* map = nullptr;
};

struct LoadedMap {
  uint32_t id = 0;
  std::vector<uint32_t> agents;
  Map map;
};

struct LoadedSnapshot {
  uint32_t format_version = 0;
  SnapshotMetadata metadata;
  std::vector<LoadedMap> maps;
};

struct SnapshotReadOptions {
  // Refuse a snapshot built with another vocabulary (checksum differs). Unset: accept any.
  std::optional<uint64_t> vocabulary_checksum;
  // Hash every byte (detects flipped bytes anywhere; costs a pass over the file). Structure and
  // every index are verified either way, so an unhashed view is still safe to read.
  bool verify_content_hash = true;
};

// Serializes the maps. Keyframes and points are written in the arenas' dense order; handles
// become dense indices. A stale point reference is written as none. Throws flatslam::Error when
// a map is inconsistent in a way the format cannot express or the buffer would exceed 2 GiB.
[[nodiscard]] std::vector<uint8_t> SerializeMapSnapshot(std::span<const SnapshotMapRef> maps,
                                                        const SnapshotMetadata& metadata);

// Writes the snapshot atomically: a temporary file in the same directory, fsync, rename, fsync of
// the directory. On any failure the previous file at path is untouched and the temporary removed.
void SaveMapSnapshot(const std::filesystem::path& path, std::span<const SnapshotMapRef> maps,
                     const SnapshotMetadata& metadata);

struct BoundingBox {
  Eigen::Vector3d min = Eigen::Vector3d::Zero(), max = Eigen::Vector3d::Zero();
  bool empty = true;
};

// A verified snapshot read in place: nothing is copied out of the mapped file except on request.
// Every accessor is bounds-safe because the constructor verified structure and indices.
class MapSnapshotView {
 public:
  // Maps the file read-only and verifies it. Throws flatslam::Error naming the file and problem.
  [[nodiscard]] static MapSnapshotView Open(const std::filesystem::path& path, const SnapshotReadOptions& options = {});
  // Verifies bytes owned by the caller (kept alive while the view is used); name is for messages.
  [[nodiscard]] static MapSnapshotView FromBytes(std::span<const uint8_t> bytes, const std::string& name,
                                                 const SnapshotReadOptions& options = {});

  MapSnapshotView(MapSnapshotView&& other) noexcept;
  MapSnapshotView& operator=(MapSnapshotView&& other) noexcept;
  MapSnapshotView(const MapSnapshotView&) = delete;
  MapSnapshotView& operator=(const MapSnapshotView&) = delete;
  ~MapSnapshotView();

  [[nodiscard]] const std::string& name() const { return name_; }
  [[nodiscard]] size_t file_size() const { return bytes_.size(); }
  [[nodiscard]] std::span<const uint8_t> bytes() const { return bytes_; }
  [[nodiscard]] uint32_t format_version() const;
  [[nodiscard]] uint64_t vocabulary_checksum() const;
  [[nodiscard]] uint64_t content_hash() const;
  [[nodiscard]] Calibration calibration() const;
  [[nodiscard]] MapScales scales() const;
  [[nodiscard]] double rgbd_virtual_baseline_m() const;  // 0: not recorded
  [[nodiscard]] CameraRefit camera_refit() const;
  [[nodiscard]] PinholeCamera given_camera() const;  // fx 0: not recorded

  [[nodiscard]] size_t map_count() const;
  [[nodiscard]] uint32_t map_id(size_t m) const;
  [[nodiscard]] std::span<const uint32_t> agents(size_t m) const;
  [[nodiscard]] size_t keyframe_count(size_t m) const;
  [[nodiscard]] size_t point_count(size_t m) const;
  [[nodiscard]] size_t observation_count(size_t m) const;
  [[nodiscard]] size_t keypoint_count(size_t m) const;  // summed over the map's keyframes
  // Of the map points' positions.
  [[nodiscard]] BoundingBox bounds(size_t m) const;
  [[nodiscard]] Eigen::Vector3d point_position(size_t m, size_t i) const;
  // Keyframe poses as T_world_cam, sorted by time (only `agent`'s keyframes when given).
  [[nodiscard]] Trajectory KeyFrameTrajectory(size_t m, std::optional<uint32_t> agent = std::nullopt) const;
  // A checkpoint's session without its trajectory (frames stays empty; LoadMapSnapshot gives it
  // with handles); nullopt for a snapshot that is not a checkpoint.
  [[nodiscard]] std::optional<SnapshotSession> session_summary() const;
  [[nodiscard]] size_t session_frame_count() const;

  // The verified flatbuffers root and segments, for readers that want every field in place.
  [[nodiscard]] const schema::MapSnapshot& root() const { return *root_; }
  [[nodiscard]] const schema::MapSegment& segment(size_t m) const;

 private:
  MapSnapshotView() = default;
  void Verify(const SnapshotReadOptions& options);

  std::string name_;
  std::span<const uint8_t> bytes_;
  MappedFile file_;  // the mapped file this view owns, or none (FromBytes)
  const schema::MapSnapshot* root_ = nullptr;
};

// Verifies the file (see MapSnapshotView) and rebuilds every map in fresh arenas: keyframe i and
// point i of a segment get dense index i, keyframe ids are kept. Map::Validate() must pass, else
// the file is refused. Throws flatslam::Error naming the file and problem.
[[nodiscard]] LoadedSnapshot LoadMapSnapshot(const std::filesystem::path& path,
                                             const SnapshotReadOptions& options = {});
[[nodiscard]] LoadedSnapshot LoadMapSnapshotFromBytes(std::span<const uint8_t> bytes, const std::string& name,
                                                      const SnapshotReadOptions& options = {});
[[nodiscard]] LoadedSnapshot LoadMapSnapshot(const MapSnapshotView& view);

// The hash stored in content_hash: 64-bit, four lanes of multiply-rotate over 32-byte blocks.
[[nodiscard]] uint64_t SnapshotHash(std::span<const uint8_t> bytes, size_t skip_offset, size_t skip_size);

}  // namespace flatslam
