#!/usr/bin/env bash
# Map merge benchmark: builds two maps of the synthetic town from four stereo sessions (agents 0
# and 1 of the town, each driven twice with different image noise), joins each pair of sessions
# into one map, then times `flatslam map merge` of the two joined maps (every keyframe of one
# overlaps the other). Prints the merge summary and the keyframe counts.
# Sessions already in WORK_DIR are reused. They run with `revisit_radius=0` (ORB-SLAM2's keyframe
# rules alone), so each joined map holds about 500 keyframes, the size the merge is timed at; with
# the default revisit rule the same sessions make about 400.
# usage: bench/merge_bench.sh [BUILD_DIR] [WORK_DIR] [DURATION_S_SEED1] [DURATION_S_SEED2]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
work="${2:-$(mktemp -d)}"
durations=("" "${3:-200}" "${4:-120}")
app="$build/apps/flatslam"
mkdir -p "$work"

session() {  # agent seed id
  local file="$work/town_a$1_s$2.fsmap"
  [[ -f "$file" ]] || "$app" run "synth:town:agent=$1,duration=${durations[$2]},seed=$2" --agent "$3" --quiet \
    --set revisit_radius=0 --save-map "$file" | grep -E '^(map|ATE) '
}
session 0 1 0
session 1 1 1
session 0 2 2
session 1 2 3
"$app" map merge "$work/town_a0_s1.fsmap" "$work/town_a1_s1.fsmap" -o "$work/town_s1.fsmap" | grep -E '^(output|time)'
"$app" map merge "$work/town_a0_s2.fsmap" "$work/town_a1_s2.fsmap" -o "$work/town_s2.fsmap" | grep -E '^(output|time)'
echo "== merge of the two joined maps (default: every keyframe free in the weld)"
/usr/bin/time -f "wall %e s, peak RSS %M KiB" "$app" map merge "$work/town_s1.fsmap" "$work/town_s2.fsmap" -o "$work/town_all.fsmap"
echo "== same, --local-weld (seam neighbourhoods only)"
/usr/bin/time -f "wall %e s, peak RSS %M KiB" "$app" map merge "$work/town_s1.fsmap" "$work/town_s2.fsmap" --local-weld -o "$work/town_all_local.fsmap"
