#!/bin/bash
# A flatslam batch split into slices on one host with GNU parallel (Debian package `parallel`):
# each slice is its own process, so a crash costs one slice; then the slices are joined.
#   docs/batch/parallel.sh INPUTS OUT [SLICES]
# FLATSLAM names the executable (default flatslam on PATH). One batch process with --jobs does
# the same work in one process; slices are for isolation, or to mimic a cluster run locally.
# The exit code is flatslam's: 1 when any sequence failed.
set -uo pipefail
inputs="${1:?usage: parallel.sh INPUTS OUT [SLICES]}"
out="${2:?usage: parallel.sh INPUTS OUT [SLICES]}"
slices="${3:-2}"
flatslam="${FLATSLAM:-flatslam}"
mkdir -p "$out/logs"
status=0
seq 0 $((slices - 1)) | parallel --halt never -j "$slices" \
  "$flatslam" batch "$inputs" --shard "{}/$slices" --jobs 2 --quiet --out "$out/shard-{}" \
  ">" "$out/logs/shard-{}.log" "2>&1" || status=1
"$flatslam" batch --collect "$out"/shard-* --out "$out/all" || status=$?
exit "$status"
