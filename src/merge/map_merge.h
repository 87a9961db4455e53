// Map merging: place recognition between maps built by different agents or sessions, a
// verified Sim(3)/SE(3) alignment, and a merge that appends one map into another through a
// handle remap, fuses duplicate points across the seam, welds the seam (a bundle adjustment
// around it), then bends the map appended to every seam (essential graph; the map merged into
// holds). A merge of several maps ends each merged map with a bundle adjustment of the whole
// map. Maps that share no verified place are left apart.
// Concurrency: each call owns the maps it is given; place recognition runs queries on TBB
// workers (reads only), as do the whole-map adjustment's conjugate-gradient products
// (bundle_adjustment.num_threads); everything that writes a map is serial.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "ecs/map.h"
#include "io/calibration.h"
#include "io/orb_settings.h"
#include "io/types.h"
#include "optimization/bundle_adjustment.h"
#include "mapping/map_bundle_adjustment.h"
#include "matching/matcher.h"
#include "merge/merged_loops.h"
#include "geometry/similarity.h"

namespace flatslam {

class Vocabulary;

// The camera the maps were built with (one calibration shared by every map merged).
struct MergeCamera {
  CameraGeometry geometry;
  MapScales scales;
  bool monocular = false;        // Sim(3) alignment; otherwise SE(3) with scale fixed to 1
  StereoDepthRule stereo_depth;  // which stereo observations the weld keeps as stereo
  // What loop closing in the merged map runs with (a SLAM context).
  Calibration calibration;
  double rgbd_virtual_baseline_m = 0;
  double far_stereo_baselines = kFarStereoBaselines;

  // From a snapshot's calibration and scales; RGB-D keyframes carry a virtual right image at
  // rgbd_virtual_baseline_m (the value the maps were built with; SnapshotMetadata records it).
  // Stereo deeper than far_stereo_baselines x baseline is optimized as monocular, as in SLAM
  // (SlamOptions::far_stereo_baselines; snapshots do not record it, so the default unless told).
  [[nodiscard]] static MergeCamera FromCalibration(const Calibration& calibration, const MapScales& scales,
                                                   double rgbd_virtual_baseline_m,
                                                   double far_stereo_baselines = kFarStereoBaselines);
};

struct MapMergeOptions {
  MatcherOptions matcher;
  size_t candidates_per_keyframe = 3;  // place-recognition candidates verified per query keyframe
  int min_bow_matches = 20;            // bag-of-words matches needed before RANSAC
  int min_matches = 40;                // map points matched after the guided Sim(3)/SE(3) search
  int min_consistent_pairs = 3;        // independent keyframe pairs (no keyframe used twice) agreeing
  double max_rotation_disagreement_deg = 5;
  // Two pair transforms agree when they place each other's keyframes within this fraction of the
  // scene depth seen by the pairs, plus drift_fraction of the distance between the pairs.
  double max_position_disagreement = 0.15;
  double drift_fraction = 0.05;
  double max_scale_disagreement = 0.1;  // monocular: |s_i / s_j - 1|
  int ransac_iterations = 300;
  size_t weld_neighbours = 10;  // covisible keyframes freed with each seam keyframe in the weld
  // The weld window: seam pairs strongest first, each freeing its two keyframes and their
  // weld_neighbours best covisible ones, until this many keyframes are free. About 25 keyframes on
  // each side of the seam, the window ORB-SLAM3 welds a merge with; the essential graph then carries
  // the correction to every other keyframe of the map merged in (the map merged into holds). The
  // weld's cost follows the window, not the maps.
  size_t max_weld_keyframes = 50;
  // After its merges (and its loops, with close_loops), each output map that joined several
  // inputs is adjusted as a whole, as ORB-SLAM3 follows a merge with a global bundle adjustment:
  // every keyframe free but the oldest of the first map (it holds the frame); this many robust
  // Levenberg-Marquardt iterations, outlier classification, then as many again (0 skips it;
  // conjugate gradients on the reduced camera system beyond bundle_adjustment.schur_lm_max_poses
  // free keyframes, below it the own solver's factorization). The essential graph moves each map
  // merged in rigidly between its seams and holds the first; the adjustment lets every map's
  // view of the points it shares with the others correct their shapes, which no pose graph can.
  // An input that carries drift its own loop closing left (visible where it meets the others) is
  // spread over every map by it: close_loops takes such drift out first. Its time follows the
  // whole map (docs/STATUS.md, "Map merge": figures).
  int adjust_iterations = 2;
  // Refine: the adjustment runs bundle_adjustment's passes instead (5 robust iterations, outlier
  // classification, 10 more), to convergence.
  bool refine = false;
  int pose_graph_iterations = 20;
  int essential_graph_min_covisibility = 100;  // within each map (SlamOptions' of the same name)
  BundleAdjustmentOptions bundle_adjustment;
  uint64_t seed = 1;  // RANSAC sampling (each query keyframe gets its own stream)
  // After the merges, close loops in every output map that joined several inputs
  // (merge/merged_loops.h): where the maps met again beyond the seams, or a map's own loop was
  // never closed. Costs a loop search per keyframe (about 0.5 s for 350 keyframes when nothing
  // is found, plus 0.4 s per loop closed).
  bool close_loops = false;
  // After a replay that closed loops, a bundle adjustment of the loops' agents, the other agents
  // held (as a session runs a global one after its loops). Its time follows those agents' maps
  // (seconds at a few hundred keyframes beside running agents): the map server's live merges leave
  // it to their final merge.
  bool adjust_after_loops = true;

  // The first requirement a field breaks, as its condition's text (empty: valid).
  [[nodiscard]] std::string Problem() const;
  [[nodiscard]] bool Check() const { return Problem().empty(); }
};

// Bag of words of every keyframe, from its descriptors (snapshots do not store them).
// missing_only: only keyframes without one (a map whose bags were computed with this vocabulary,
// as a live map server's are).
void ComputeKeyFrameBow(Map& map, const Vocabulary& vocabulary, bool missing_only = false);

// A keyframe of the `from` map and a keyframe of the `into` map that see the same place.
struct MergePair {
  KeyFrameHandle from_keyframe, into_keyframe;
  Similarity3 S_into_from;           // world of from -> world of into, as this pair sees it
  std::vector<PointHandle> matched;  // per keypoint of from_keyframe: the into-map point, or null
  int matches = 0;
  double scene_depth = 0;  // median depth of the matched into points, into units
};

struct MapOverlap {
  bool found = false;
  size_t queries = 0;               // from keyframes with a bag of words
  size_t candidates = 0;            // place-recognition candidates verified geometrically
  std::vector<MergePair> verified;  // every pair that passed the geometric check
  std::vector<size_t> consistent;   // indices into verified: the largest agreeing group
  size_t independent_pairs = 0;     // of the consistent group, pairs with distinct keyframes
  Similarity3 S_into_from;          // fitted on every correspondence of the consistent group
  size_t correspondences = 0;       // point pairs used for that fit
  double residual_rms = 0;          // of those point pairs after the fit, into units
};

// Finds where `from` overlaps `into`: every from keyframe queries a keyframe database of into;
// candidates are verified by bag-of-words matching, RANSAC of the Sim(3)/SE(3) and a guided
// search that must reach min_matches; the verified pairs must agree on one transform, at least
// min_consistent_pairs of them with distinct keyframes. Bags of words must be computed.
// queries: the from keyframes that query (empty: every one with a bag of words).
[[nodiscard]] MapOverlap FindMapOverlap(const Map& into, const Map& from, const Vocabulary& vocabulary,
                                        const MergeCamera& camera, const MapMergeOptions& options,
                                        std::span<const KeyFrameHandle> queries = {});

// Where each entity of the source map went: indexed by the source handle's slot index.
struct MapRemap {
  std::vector<KeyFrameHandle> keyframes;
  std::vector<PointHandle> points;

  [[nodiscard]] KeyFrameHandle operator()(const Map& from, KeyFrameHandle h) const;
  [[nodiscard]] PointHandle operator()(const Map& from, PointHandle h) const;
};

// Copies every keyframe and point of `from` into `into`, transformed by S_into_from (poses keep
// their rigidity; with a scale, positions, depths and distance ranges scale). Every handle-typed
// field (keypoint points, observations, covisibility, spanning tree, loop edges, references) is
// rewritten to the fresh handles. Keyframes get new ids after into's, in from's id order.
MapRemap AppendMap(Map& into, const Map& from, const Similarity3& S_into_from);

// A keyframe's own columns (identity, keypoints, descriptors, depths, bag of words, agent) with
// its pose moved by S_into_from (depths scaled with it), every handle null and no graph: what
// AppendMap and a live map server's growing merge (merge/live_merge.h) add to a map.
[[nodiscard]] KeyFrame MovedKeyFrameColumns(const KeyFrame& source, const Similarity3& S_into_from);

struct MergeReport {
  MapOverlap overlap;
  bool merged = false;
  size_t keyframes_added = 0, points_added = 0;
  size_t points_fused = 0;      // duplicate points merged across the seam
  size_t loop_edges = 0;        // added between matched keyframes
  size_t welded_keyframes = 0;  // free in the seam bundle adjustment (the weld window)
  size_t weld_outliers = 0;     // observations dropped by it
  double place_ms = 0, merge_ms = 0;
  // Parts of merge_ms: append and fuse, covisibility and essential graph, weld bundle adjustment.
  double fuse_ms = 0, graph_ms = 0, weld_ms = 0;
};

// The keyframes a weld frees (SelectWeldWindow): seam pairs in the order given (strongest
// first), each adding its two keyframes and their `neighbours` best covisible keyframes, until
// the window holds max_keyframes (a pair is added whole, so the last one may pass it by up to
// 2 + 2 x neighbours). Dead handles are skipped.
struct SeamPair {
  KeyFrameHandle into_keyframe, from_keyframe;  // both in the merged map
};
[[nodiscard]] std::vector<KeyFrameHandle> SelectWeldWindow(const Map& map, std::span<const SeamPair> seam,
                                                           size_t neighbours, size_t max_keyframes);

// The weld's bundle adjustment: `free` keyframes free (`anchor` among them held, or none), every
// other keyframe that sees their points fixed; outlier observations are erased and the free
// keyframes' covisibility recomputed. Returns how many observations it erased.
size_t WeldBundleAdjustment(Map& map, const MergeCamera& camera, const BundleAdjustmentOptions& options,
                            std::vector<KeyFrameHandle> free, KeyFrameHandle anchor);

// Merges `from` into `into` when they overlap (into's frame is kept); leaves `into` untouched
// otherwise. `from` is never modified. Both maps need bags of words (ComputeKeyFrameBow).
[[nodiscard]] MergeReport MergeMaps(Map& into, const Map& from, const Vocabulary& vocabulary, const MergeCamera& camera,
                                    const MapMergeOptions& options);

// The same with the overlap already found by FindMapOverlap(into, from, ...) on these two maps
// as they are now.
[[nodiscard]] MergeReport MergeMaps(Map& into, const Map& from, MapOverlap overlap, const MergeCamera& camera,
                                    const MapMergeOptions& options);

// Overlap between two input maps, as place recognition measured it before any merge.
struct OverlapEdge {
  size_t a = 0, b = 0;           // input indices, a < b (a was the into side)
  size_t independent_pairs = 0;  // agreeing keyframe pairs with distinct keyframes
  size_t correspondences = 0;    // point pairs of the fitted transform
  bool found = false;            // enough agreeing pairs to merge
};

// One merge of the plan: input `from` joins the group whose first input is `root`.
struct MergeStep {
  size_t root = 0, from = 0;
  size_t edge = 0;  // index of the OverlapEdge it follows
};

// The order to merge `count` inputs in: a maximum spanning forest of the overlap graph (edges
// that found an overlap, weighted by independent pairs, then correspondences), each tree rooted at
// its lowest input (whose frame the merged map keeps) and grown strongest edge first from the
// inputs already joined (Prim). Inputs on no edge are not in any step and stay separate.
[[nodiscard]] std::vector<MergeStep> PlanMergeOrder(size_t count, const std::vector<OverlapEdge>& edges);

struct MergeAttempt {
  std::vector<size_t> into, from;  // input maps already in each side (into keeps its frame)
  MergeReport report;
};

// The adjustment of a merged map as a whole (MapMergeOptions::adjust_iterations).
struct MergedMapAdjustment {
  size_t keyframes = 0;  // free (0: not adjusted)
  size_t outliers = 0;   // observations it erased
  bool refined = false;  // full passes (MapMergeOptions::refine)
  double ms = 0;
};

// Adjusts a merged map as a whole (MapMergeOptions::adjust_iterations): every keyframe free but
// the one with the lowest id, which holds the frame.
[[nodiscard]] MergedMapAdjustment AdjustMergedMap(Map& map, const MergeCamera& camera, const MapMergeOptions& options);

// What re-expressing a map in another camera did (ReexpressMapCamera).
struct CameraChange {
  size_t keypoints = 0;            // keypoints moved
  double max_shift_px = 0;         // the largest move of one
  size_t observations_erased = 0;  // their keypoint left the new camera's image
  MergedMapAdjustment adjustment;  // the map alone, in the new camera
};

// Re-expresses a map whose keypoints were measured through refinement `from` of a camera in
// refinement `to` of the same camera (two runs that refined one lens differently saw one given
// image through two models): every keypoint moves through the given image, observations whose
// keypoint leaves `to`'s image are erased, then the map is adjusted alone in `to` (camera, whose
// calibration is to.camera()) to convergence, since each keypoint moved by the model's error,
// and that is systematic, not noise. The map can then merge with maps built through `to`.
// Concurrency: exclusive access to map; keyframes move on TBB workers, each its own.
[[nodiscard]] CameraChange ReexpressMapCamera(Map& map, const RefinedCamera& from, const RefinedCamera& to,
                                              const MergeCamera& camera, const MapMergeOptions& options);

// A map measured through refinement `refit` of the camera `given`, moved into `refit` followed by
// `more` (ThenRefit: the refinement its own camera check asks for) by ReexpressMapCamera, with
// the default merge options on every thread of the calling arena. The refinement composed, the
// calibration the map is then in (`calibration`'s with the refined camera), and what moved.
struct MapCameraRefinement {
  CameraRefit refit;
  Calibration calibration;
  CameraChange change;
};
[[nodiscard]] MapCameraRefinement RefineMapCamera(Map& map, const Calibration& calibration, const MapScales& scales,
                                                  const PinholeCamera& given, const CameraRefit& refit,
                                                  const CameraRefit& more);

struct MultiMapMerge {
  std::vector<Map> maps;                         // one per group of overlapping inputs
  std::vector<std::vector<size_t>> members;      // input maps of each output map, first = its frame
  std::vector<OverlapEdge> overlaps;             // every pair of inputs, as first measured
  std::vector<MergeAttempt> attempts;            // in the order they were made
  std::vector<MergedMapAdjustment> adjustments;  // per output map, after its merges and loops
  std::vector<MergedMapLoops> loops;             // per output map, with close_loops (else empty)
  // Per output map, with close_loops: what its loop closing built, to continue it over keyframes
  // added later (empty for a map of one input, where no loop was searched).
  std::vector<MergedMapLoopCloser> loop_closers;
};

// What loop closing in a merged map runs with: a SLAM context of the camera, default options.
[[nodiscard]] SystemContext MergedMapContext(const MergeCamera& camera);

// Merges several maps (bags of words are computed where a keyframe has none; one it has must come
// from this vocabulary): place recognition between every pair of inputs (the overlap graph), then
// the merges of PlanMergeOrder. A step whose group has grown since the pair was measured finds
// the overlap again against the whole group. An input whose merge fails, or that overlaps
// nothing, is kept as its own map in its own frame.
[[nodiscard]] MultiMapMerge MergeAllMaps(std::vector<Map> maps, const Vocabulary& vocabulary, const MergeCamera& camera,
                                         const MapMergeOptions& options);

}  // namespace flatslam
