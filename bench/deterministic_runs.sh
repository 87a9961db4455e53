#!/usr/bin/env bash
# Writes the trajectories of the runs whose output must not change when the core is restructured
# (`--deterministic`: local mapping inline, same input, same output), one file per run, so that
# two builds can be compared byte for byte:
#   bench/deterministic_runs.sh BUILD_A /tmp/a; bench/deterministic_runs.sh BUILD_B /tmp/b
#   diff -r /tmp/a /tmp/b
# usage: bench/deterministic_runs.sh [BUILD_DIR] OUT_DIR [DATASETS_DIR]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
out="${2:?usage: bench/deterministic_runs.sh BUILD_DIR OUT_DIR [DATASETS_DIR]}"
datasets="${3:-$here/../shared/datasets}"
app="$build/apps/flatslam"

runs=(
  "kitti07-mono|$datasets/kitti/sequences/07|--sensor mono --features 2000"
  "kitti06-stereo|$datasets/kitti/sequences/06|"
  "room-stereo|synth:room|"
  "room-rgbd|synth:room:sensor=rgbd|"
  "town-agent1|synth:town:agent=1|"
)
mkdir -p "$out"
for entry in "${runs[@]}"; do
  IFS='|' read -r name spec extra <<<"$entry"
  dir=$(mktemp -d)
  # shellcheck disable=SC2086
  "$app" run "$spec" $extra --deterministic --quiet --out "$dir" >"$out/$name.summary"
  cp "$dir/trajectory.tum" "$out/$name.tum"
  cp "$dir/keyframes.tum" "$out/$name.keyframes.tum" 2>/dev/null || true
  rm -rf "$dir"
  printf "%-16s %s\n" "$name" "$(awk '/^ATE/' "$out/$name.summary")"
done
