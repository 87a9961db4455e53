// What a batch runs: sequences named by dataset folders, folders of dataset folders, synth:SPEC
// or a manifest file, each with its own sensor, settings and options.
// Concurrency: free functions; they read the file system.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include "io/types.h"

namespace flatslam {

// One sequence to run, as `flatslam run` would be given it.
struct SequenceSpec {
  std::string name;              // unique in a batch; names the sequence's output folder
  std::string dataset;           // a dataset folder or synth:SPEC (OpenDataset)
  std::optional<Sensor> sensor;  // empty: the richest the dataset offers
  std::string settings;          // an ORB-SLAM2/3 settings file (--settings), or empty
  std::string config;            // a SLAM options file (--config), or empty
  std::vector<std::string> set;  // KEY=VALUE options (--set), applied last
  std::optional<uint64_t> seed;  // synthetic scenes' noise (empty: 1)
  size_t max_frames = 0;         // 0 = every frame
  // Monocular: run with the camera as given (--keep-camera), not checked against the young map
  // (SlamRunOptions::check_camera). Empty: the batch's default (check).
  std::optional<bool> keep_camera;
  // Monocular: run with the camera this saved map's session used (--camera-from), or empty.
  std::string camera_from;
  std::string where;             // where it was declared ("FILE:LINE" for a manifest), for errors
};

// Reads a manifest. Two forms, told apart by the first line that is not blank or a comment:
//
//   Lines: one sequence per line, "DATASET [--name N] [--sensor S] [--settings F] [--config F]
//          [--set K=V,...] [--seed N] [--max-frames N] [--keep-camera] [--camera-from MAP]";
//          '#' starts a comment
//          (--keep-camera alone means true; --keep-camera=false is also read).
//
//   YAML (a list of mappings, optionally under "sequences:"):
//          - path: DATASET        (required; also "dataset:")
//            name: N
//            sensor: stereo
//            settings: F
//            config: F
//            seed: 2
//            max_frames: 100
//            keep_camera: true    (true/false, yes/no, 1/0)
//            camera_from: MAP     (a saved map: its session's camera)
//            options:             (a mapping of option keys, or one "K=V,K=V" string)
//              orb.features: 2000
//
// Relative paths are taken from the manifest's folder. Throws flatslam::Error naming the file and
// line of anything it cannot read (an unknown key or flag, a missing path, a bad number).
[[nodiscard]] std::vector<SequenceSpec> ReadManifest(const std::filesystem::path& path);

// Expands the inputs of `flatslam batch` in order: synth:SPEC is one sequence; a dataset folder
// (KITTI sequence, EuRoC, TUM) is one; a folder of dataset folders (or a KITTI root holding
// sequences/) is one per dataset in it, in name order; any other file is a manifest. `defaults`
// gives what an input does not say (sensor, options). Names are made unique (a folder's base
// name, suffixed -2, -3, ... on a clash) and safe as folder names. Throws flatslam::Error naming
// an input that is none of these, or when there is no sequence at all.
[[nodiscard]] std::vector<SequenceSpec> ExpandBatchInputs(const std::vector<std::string>& inputs,
                                                          const SequenceSpec& defaults);

// The deterministic slice `index` of `count` (--shard I/N): the sequences at positions p with
// p % count == index, so every shard gets a like mix of a sorted input list.
[[nodiscard]] std::vector<size_t> ShardPositions(size_t sequences, size_t index, size_t count);

}  // namespace flatslam
