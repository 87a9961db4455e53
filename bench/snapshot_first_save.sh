#!/usr/bin/env bash
# The first map save of a process (what `flatslam run --save-map` does), on the KITTI-00-sized
# map of bench_snapshot: RUNS fresh processes, the page cache flushed (sync) before each. Prints
# one line a run; the in-process benchmark (bench_snapshot) shows repeated saves. Each run is
# followed by the floor the disk sets: dd writing as many bytes to a new file, then fsync.
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
  bytes=$(stat -c %s "$file")
  rm -f "$file"
  sync
  sleep 2
  start=$(date +%s%N)
  dd if=/dev/zero of="$file" bs=1M count=$(((bytes + 1048575) / 1048576)) conv=fsync status=none
  awk -v ns=$(($(date +%s%N) - start)) 'BEGIN { printf "  dd of as many bytes, then fsync: %.1f ms\n", ns / 1e6 }'
done
rm -f "$file"
