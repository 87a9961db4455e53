#!/usr/bin/env bash
# Place recognition end to end: loop closing on 60 s synthetic loops (stereo, RGB-D, monocular;
# a lap of the room takes about 26 s) with and without loop closing, a kidnapping (60 dropped
# frames landing in a mapped place), and KITTI 07 monocular with tracking forced lost at frame 80.
# Prints one row per run: frames tracked/lost, relocalizations, new map segments, loops, loops
# whose keyframes are more than 2 m apart in the ground truth (false), ATE, frames/s.
# usage: bench/place_bench.sh [BUILD_DIR] [DATASETS_DIR]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
datasets="${2:-$here/../shared/datasets}"
app="$build/apps/flatslam"

runs=(
  "room-stereo-noloop|synth:room:duration=60|--no-loop-closing"
  "room-stereo-loop|synth:room:duration=60|"
  "room-rgbd-noloop|synth:room:duration=60,sensor=rgbd|--no-loop-closing"
  "room-rgbd-loop|synth:room:duration=60,sensor=rgbd|"
  "room-mono-noloop|synth:room:duration=60,sensor=mono|--no-loop-closing"
  "room-mono-loop|synth:room:duration=60,sensor=mono|"
  "room-stereo-kidnap|synth:room:duration=40|--skip 600:660 --no-loop-closing"
  "kitti07-mono-lose80|$datasets/kitti/sequences/07|--features 2000 --lose-at 80"
)

printf "%-20s %7s %5s %6s %6s %6s %6s %9s %7s %9s %9s %s\n" run tracked lost reloc reinit loops false ATE_m ATE_% ATE_sim3 frames/s first_loop
for entry in "${runs[@]}"; do
  IFS='|' read -r name spec extra <<<"$entry"
  # shellcheck disable=SC2086
  summary=$("$app" run "$spec" $extra --quiet)
  tracked=$(awk '/^frames/{print $2}' <<<"$summary")
  lost=$(awk '/^frames/{print $4}' <<<"$summary")
  reloc=$(awk '/^places/{for(i=1;i<=NF;i++) if($i=="relocalizations,") print $(i-1)}' <<<"$summary")
  reinit=$(awk '/^places/{for(i=1;i<=NF;i++) if($i=="new") print $(i-1)}' <<<"$summary")
  loops=$(awk '/^places/{for(i=1;i<=NF;i++) if($i=="loop") print $(i-1)}' <<<"$summary")
  false_loops=$(awk '/^  loop/{for(i=1;i<=NF;i++) if($i=="centres" && $(i+1)+0 > 2.0) n++} END{print n+0}' <<<"$summary")
  first=$(awk '/^  loop/{print $3 "->" $6; exit}' <<<"$summary" | tr -d ':')
  fps=$(awk '/^throughput/{print $2}' <<<"$summary")
  ate=$(awk '/^ATE/{print $2}' <<<"$summary")
  pct=$(awk '/^ATE/{gsub(/\(/,"",$0); for(i=1;i<=NF;i++) if($i ~ /%$/) {print $i; exit}}' <<<"$summary")
  sim3=$(awk '/^ATE/{for(i=1;i<=NF;i++) if($i=="Sim(3)") {print $(i+1); exit}}' <<<"$summary")
  printf "%-20s %7s %5s %6s %6s %6s %6s %9s %7s %9s %9s %s\n" "$name" "$tracked" "$lost" "$reloc" "$reinit" \
    "$loops" "$false_loops" "$ate" "$pct" "$sim3" "$fps" "${first:--}"
done
