#!/usr/bin/env bash
# A long session with checkpoints: stereo SLAM over FRAMES frames of the synthetic room (a lap of
# the room takes about 26 s, 520 frames at 20 Hz) with `--checkpoint-every SECONDS`. Prints the
# resident set at the end of every LAPS_PER_ROW-th lap (from stats.csv), frames lost, the
# checkpoint line of the summary (copies, longest frame while checkpointing against the median),
# and whether the resident set at the end is within 5% of the one after the second lap.
# usage: bench/long_session.sh [BUILD_DIR] [FRAMES] [SECONDS] [LAPS_PER_ROW]
# 100,000 frames take about 25 min on two cores.
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
frames="${2:-100000}"
every="${3:-60}"
laps_per_row="${4:-10}"
app="$build/apps/flatslam"
lap_frames=520
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT

duration=$(( (frames + 19) / 20 ))
echo "session: synth:room:duration=$duration ($frames frames), checkpoint every $every s"
/usr/bin/time -v "$app" run "synth:room:duration=$duration" --quiet --out "$work/out" \
  --checkpoint "$work/session.fsmap" --checkpoint-every "$every" >"$work/summary" 2>"$work/stderr"
grep -E "^(frames|map|time|throughput|checkpoints|peak RSS|ATE|warnings)" "$work/summary"
grep -E "Maximum resident|Elapsed" "$work/stderr" || true
"$app" map verify "$work/session.fsmap"

# stats.csv columns: frame,t_ns,state,...,rss_mib (13),heap_mib (14),map_keyframes (15),map_points (16)
awk -F, -v lap="$lap_frames" -v every="$laps_per_row" '
  NR == 1 { next }
  $3 == "lost" { lost++ }
  { last_rss = $13; last_heap = $14; last_kf = $15; last_pts = $16; n = $1 + 1 }
  ($1 + 1) % lap == 0 {
    l = ($1 + 1) / lap
    rss[l] = $13
    if (l == 2) lap2 = $13
    if (l % every == 0 || l <= 3) printf "lap %4d  frame %6d  RSS %7.1f MiB  heap %7.1f MiB  keyframes %5d  points %6d\n", l, $1, $13, $14, $15, $16
  }
  END {
    printf "end       frame %6d  RSS %7.1f MiB  heap %7.1f MiB  keyframes %5d  points %6d\n", n - 1, last_rss, last_heap, last_kf, last_pts
    printf "frames lost: %d\n", lost
    if (lap2 > 0) {
      growth = 100 * (last_rss - lap2) / lap2
      printf "RSS end vs after lap 2: %+.2f%% (%s: within 5%%)\n", growth, (growth <= 5 && growth >= -5) ? "pass" : "FAIL"
    }
  }' "$work/out/stats.csv"
