// The map world: keyframes and map points in generational arenas, observations as flat
// {keyframe, keypoint} tables, covisibility weights and the spanning tree as handle lists.
// Concurrency: no internal locking. The caller (the pipeline schedule) grants either one
// writer or many readers; see MapLock in systems for how tracking and mapping share it.
#pragma once

#include <cstdint>
#include <span>
#include <utility>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "ecs/arena.h"
#include "ecs/bow.h"
#include "ecs/descriptor.h"
#include "ecs/handle.h"
#include "ecs/shared_column.h"

namespace flatslam {

struct KeyFrame;
struct MapPoint;
using KeyFrameHandle = Handle<KeyFrame>;
using PointHandle = Handle<MapPoint>;

// One sighting of a map point: keypoint `keypoint` of `keyframe`.
struct Observation {
  KeyFrameHandle keyframe;
  uint32_t keypoint = 0;
};

struct KeyFrame {
  // Creation order within its map: ages counted in keyframes made since (recent-point culling,
  // revisits) and tie-breaking; never a time.
  uint64_t id = 0;
  size_t frame_index = 0;  // index of the input frame it was made from
  int64_t t_ns = 0;
  Eigen::Isometry3d T_cam_world = Eigen::Isometry3d::Identity();

  // Per-keypoint struct-of-arrays, all of size() entries.
  // The keypoints as measured: written when the keyframe is made, shared by copies of the map.
  SharedColumn<Eigen::Vector2f> uv;  // undistorted pixel, level-0 coordinates
  SharedColumn<float> right_u;       // stereo/RGB-D: x in the (virtual) right image, -1 none
  SharedColumn<float> depth;         // metres, -1 none
  SharedColumn<float> angle;         // keypoint orientation, radians
  SharedColumn<uint8_t> octave;      // pyramid level
  SharedColumn<Descriptor> descriptor;
  std::vector<PointHandle> points;  // map point seen at the keypoint, null if none

  std::vector<std::pair<KeyFrameHandle, int>> covisible;  // shared points, strongest first
  KeyFrameHandle parent;                                  // spanning tree (null for a root)
  std::vector<KeyFrameHandle> children;
  std::vector<KeyFrameHandle> loop_edges;  // keyframes joined to this one by loop closure

  // Place recognition: derived from the descriptors and the vocabulary (not stored in snapshots).
  BowVector bow;
  FeatureVector bow_features;

  uint32_t agent = 0;  // the agent (robot, session) that made this keyframe

  [[nodiscard]] size_t size() const { return uv.size(); }
  [[nodiscard]] Eigen::Vector3d camera_center() const { return T_cam_world.inverse().translation(); }
  // Resizes every per-keypoint column to n (points null, right_u/depth -1).
  void resize(size_t n);
};

struct MapPoint {
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // world frame
  Descriptor descriptor{};                             // the observation closest to all others
  Eigen::Vector3d normal = Eigen::Vector3d::UnitZ();   // mean viewing direction (unit)
  float min_distance = 0, max_distance = 0;            // scale-invariance range, metres
  std::vector<Observation> observations;
  KeyFrameHandle reference;  // keyframe that created it
  uint64_t first_keyframe_id = 0;
  uint32_t visible = 1;  // frames where it should have been seen
  uint32_t found = 1;    // frames where it was matched
  // The observations changed since `descriptor` was chosen from them (Map::UpdatePointStats
  // chooses it again only then: a keyframe's descriptors never change, so the choice is a
  // function of the observations and their order).
  bool descriptor_stale = true;

  [[nodiscard]] float found_ratio() const { return static_cast<float>(found) / static_cast<float>(visible); }
};

// Scale pyramid facts the map needs to keep distance ranges (see ScalePyramid in systems).
// A pose in 28 bytes (single precision: 1e-7 relative, 0.1 mm at 1 km from the origin).
struct CompactPose {
  float q[4] = {0, 0, 0, 1};  // x y z w
  float t[3] = {0, 0, 0};
  CompactPose() = default;
  explicit CompactPose(const Eigen::Isometry3d& T) {
    const Eigen::Quaternionf rotation = Eigen::Quaterniond(T.linear()).normalized().cast<float>();
    q[0] = rotation.x(), q[1] = rotation.y(), q[2] = rotation.z(), q[3] = rotation.w();
    for (int k = 0; k < 3; ++k) t[k] = static_cast<float>(T.translation()[k]);
  }
  [[nodiscard]] Eigen::Isometry3d isometry() const {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::Quaterniond(q[3], q[0], q[1], q[2]).normalized().toRotationMatrix();
    T.translation() = Eigen::Vector3d(t[0], t[1], t[2]);
    return T;
  }
};

// A tracked frame's pose as a session keeps it: relative to a reference keyframe, so that map
// corrections move it, with the pose it was tracked at for when no live keyframe is left to
// follow. 72 bytes: a session of 100,000 frames keeps 7 MiB of them.
struct AnchoredFramePose {
  int64_t t_ns = 0;
  KeyFrameHandle reference;
  CompactPose T_cam_ref;
  CompactPose T_cam_world;  // at tracking time
};

struct MapScales {
  float scale_factor = 1.2f;
  int levels = 8;
};

// A camera pose (T_cam_world) after its world moved by X_new = scale * R X_old + t (T_new_old =
// [R|t]): the same centre and orientation in the new world, in a camera frame whose distances
// scale with it (rotation R_cw R^T, translation scale * t_cw - R_cw R^T t).
[[nodiscard]] Eigen::Isometry3d MovedCameraPose(const Eigen::Isometry3d& T_cam_world, const Eigen::Isometry3d& T_new_old,
                                                double scale);

class Map {
 public:
  [[nodiscard]] KeyFrameHandle AddKeyFrame(KeyFrame&& keyframe);
  // Adds a keyframe keeping its id (loading a saved map); later AddKeyFrame ids come after it.
  [[nodiscard]] KeyFrameHandle RestoreKeyFrame(KeyFrame&& keyframe);
  [[nodiscard]] PointHandle AddPoint(const Eigen::Vector3d& position, KeyFrameHandle reference);

  // Links keypoint k of kf to point p (both directions). A keypoint already bound to another
  // point, or a point already seen by kf, is an invariant error (checked).
  void AddObservation(PointHandle p, KeyFrameHandle kf, uint32_t keypoint);
  // Unlinks kf from p. A point left with fewer than min_observations sightings is erased;
  // returns true when that happened.
  bool EraseObservation(PointHandle p, KeyFrameHandle kf, size_t min_observations = 2);
  // Removes p and every keyframe slot that refers to it.
  void ErasePoint(PointHandle p);
  // Removes kf: its observations, its covisibility links, and re-parents its children.
  void EraseKeyFrame(KeyFrameHandle kf);
  // Merges `from` into `into` (duplicate points): observations move unless the keyframe
  // already sees `into`; `from` is erased. Visible/found counters add up.
  void ReplacePoint(PointHandle from, PointHandle into);

  // Binds keypoints of kf to matched points (matched[k] for keypoint k; null or erased entries
  // skipped): a point kf already has at k is merged into the matched one (ReplacePoint), a free
  // keypoint observes it unless kf already sees it elsewhere. Used where two places are joined.
  void BindMatchedPoints(KeyFrameHandle kf, std::span<const PointHandle> matched);
  // Joins a and b by a loop edge (both directions; once).
  void AddLoopEdge(KeyFrameHandle a, KeyFrameHandle b);
  // Moves the whole map into another world frame, X_new = scale * R X_old + t (T_new_old = [R|t]):
  // every keyframe pose (MovedCameraPose) and every point (position, viewing direction, distance
  // range). Rigid with scale 1, when distances, and so everything relative, stay; with another
  // scale (a monocular map, whose scale is arbitrary) every distance scales and every angle and
  // pixel stays.
  void MoveFrame(const Eigen::Isometry3d& T_new_old, double scale = 1.0);
  // Recomputes kf's covisibility (keyframes sharing >= min_shared points; if none reach it,
  // the single best one) and mirrors the weights into the neighbours. Sets the parent of a
  // keyframe without one to its strongest neighbour.
  void UpdateCovisibility(KeyFrameHandle kf, int min_shared = 15);
  // The two halves of UpdateCovisibility, so that many keyframes can be counted at once: the
  // links kf would get, strongest first (reads only: concurrent calls are safe while nothing
  // writes the map), and writing them (as UpdateCovisibility does with them).
  using CovisibilityLinks = std::vector<std::pair<KeyFrameHandle, int>>;
  // The order every covisibility list is kept in: strongest first, ties by handle.
  [[nodiscard]] static bool StrongerLink(const std::pair<KeyFrameHandle, int>& a,
                                         const std::pair<KeyFrameHandle, int>& b) {
    return a.second != b.second ? a.second > b.second : a.first < b.first;
  }
  [[nodiscard]] CovisibilityLinks ComputeCovisibility(KeyFrameHandle kf, int min_shared = 15) const;
  void SetCovisibility(KeyFrameHandle kf, CovisibilityLinks links);
  // The n strongest covisible keyframes of kf that are still alive.
  [[nodiscard]] std::vector<KeyFrameHandle> BestCovisible(KeyFrameHandle kf, size_t n) const;
  // Recomputes normal, distance range and representative descriptor of p from its observations.
  void UpdatePointStats(PointHandle p, const MapScales& scales);

  [[nodiscard]] Arena<KeyFrame>& keyframes() { return keyframes_; }
  [[nodiscard]] const Arena<KeyFrame>& keyframes() const { return keyframes_; }
  [[nodiscard]] Arena<MapPoint>& points() { return points_; }
  [[nodiscard]] const Arena<MapPoint>& points() const { return points_; }
  [[nodiscard]] KeyFrame& keyframe(KeyFrameHandle h) { return keyframes_.get(h); }
  [[nodiscard]] const KeyFrame& keyframe(KeyFrameHandle h) const { return keyframes_.get(h); }
  [[nodiscard]] MapPoint& point(PointHandle h) { return points_.get(h); }
  [[nodiscard]] const MapPoint& point(PointHandle h) const { return points_.get(h); }

  // Checks every cross reference (keyframe slots <-> observations, covisibility symmetry,
  // spanning tree links); returns an empty string when consistent, else the first problem.
  [[nodiscard]] std::string Validate() const;

  // Makes this map a copy of `other` for a snapshot (a checkpoint): same handles and values, but
  // without bags of words. The keyframes' per-keypoint columns are shared with `other`, not
  // copied; called again and again from one live map, it reuses this map's buffers.
  void AssignForSnapshot(const Map& other);

 private:
  void RemoveCovisibilityLinks(KeyFrameHandle kf);

  Arena<KeyFrame> keyframes_;
  Arena<MapPoint> points_;
  uint64_t next_keyframe_id_ = 0;
};

}  // namespace flatslam
