#!/usr/bin/env bash
# End-to-end SLAM benchmark: runs `flatslam run` on the real KITTI stereo snippet and on
# synthetic stereo / RGB-D scenes, as fast as frames can be read, and prints one table row each
# (frames/s, median ms per stage, keyframes, ATE after SE(3) and Sim(3), scale, peak RSS).
# Monocular runs have an arbitrary scale: read their ATE_sim3.
# usage: bench/slam_bench.sh [BUILD_DIR] [DATASETS_DIR]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
datasets="${2:-$here/../shared/datasets}"
app="$build/apps/flatslam"

# "-lag3" rows let local mapping run up to 3 keyframes behind tracking (`--mapping-lag 3`):
# faster, but the result varies from run to run with the timing.
runs=(
  "kitti07-mono|$datasets/kitti/sequences/07|"
  "kitti07-mono-lag3|$datasets/kitti/sequences/07|--mapping-lag 3"
  "kitti06-stereo|$datasets/kitti/sequences/06|"
  "kitti06-stereo-lag3|$datasets/kitti/sequences/06|--mapping-lag 3"
  "room-stereo-60s|synth:room|"
  "room-rgbd-60s|synth:room:sensor=rgbd|"
  "corridor-stereo-70s|synth:corridor|"
  "street-stereo-60s|synth:street|"
)

printf "%-20s %7s %9s %10s %8s %5s %9s %8s %7s %9s %7s %8s\n" run frames frames/s extract_ms track_ms lost keyframes ATE_m ATE_% ATE_sim3 scale RSS_MiB
for entry in "${runs[@]}"; do
  IFS='|' read -r name spec extra <<<"$entry"
  out=$(mktemp -d)
  # shellcheck disable=SC2086
  summary=$("$app" run "$spec" $extra --quiet --out "$out")
  frames=$(awk '/^frames/{print $2}' <<<"$summary")
  lost=$(awk '/^frames/{print $4}' <<<"$summary")
  kfs=$(awk '/^map /{print $2}' <<<"$summary")
  fps=$(awk '/^throughput/{print $2}' <<<"$summary")
  extract=$(awk '/^time/{print $4}' <<<"$summary")
  track=$(awk '/^time/{print $10}' <<<"$summary")
  rss=$(awk '/^peak RSS/{print $3}' <<<"$summary")
  ate=$(awk '/^ATE/{print $2}' <<<"$summary")
  pct=$(awk '/^ATE/{gsub(/\(/,"",$0); for(i=1;i<=NF;i++) if($i ~ /%$/) {print $i; exit}}' <<<"$summary")
  scale=$(awk '/^ATE/{print $NF}' <<<"$summary")
  sim3=$(awk '/^ATE/{for(i=1;i<=NF;i++) if($i=="Sim(3)") {print $(i+1); exit}}' <<<"$summary")
  printf "%-20s %7s %9s %10s %8s %5s %9s %8s %7s %9s %7s %8s\n" "$name" "$frames" "$fps" "$extract" \
    "$track" "$lost" "$kfs" "$ate" "$pct" "$sim3" "$scale" "$rss"
  rm -rf "$out"
done
