#!/usr/bin/env bash
# The first map save of a process (what `flatslam run --save-map` does), on the KITTI-00-sized
# map of bench_snapshot: RUNS fresh processes, the page cache flushed (sync) before each. Prints
# one line a run; the in-process benchmark (bench_snapshot) shows repeated saves.
# usage: bench/snapshot_first_save.sh [BUILD_DIR] [RUNS] [DIR]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
runs="${2:-5}"
dir="${3:-${TMPDIR:-/tmp}}"
file="$dir/flatslam_first_save_$$.fsmap"
for ((i = 1; i <= runs; i++)); do
  rm -f "$file"
  sync
  sleep 2
  "$build/bench/bench_snapshot" --first-save "$file"
done
rm -f "$file"
