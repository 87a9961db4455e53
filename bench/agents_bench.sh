#!/usr/bin/env bash
# Live agents over DDS on one machine: a map server and three town agents at once (loopback),
# then the same three runs at once without publishing or server. Prints, per agent: keyframes and
# bytes sent (per keyframe and per second), the final map update, and the tracking time with and
# without publishing (both beside the two other agents on the same cores), and the last correction
# the agent received; for the server: each live merge while the agents ran (time, keyframes, maps
# joined), when agents met and how long after their first overlap the merged map was ready, each
# agent's end of run, messages received, the merge and save time after the agents stopped, and
# the output maps; then each agent's keyframe ATE in its own map and in the server's, and all
# three under one alignment.
# SECONDS (optional) runs every agent for that long instead (36 s for agent 0, 55 s for the others):
# after the first minute the agents drive roads they mapped, and the server grows its merged map by
# their few new keyframes instead of merging again (the "grown" live merges).
# APART_SECONDS (optional) adds a fourth agent that drives the highway for that long at the town
# agents' camera and never meets them: the server keeps its map apart and searches it for an
# overlap at every grown merge; printed: the first of those searches and the last three (keyframes
# of the run apart, keyframes that queried, time).
# usage: bench/agents_bench.sh [BUILD_DIR] [OUT_DIR] [SECONDS] [APART_SECONDS]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
out="${2:-$(mktemp -d)}"
seconds="${3:-}"
apart="${4:-}"
app="$build/apps/flatslam"
mkdir -p "$out"
town() {
  local d="$seconds"
  [ -n "$d" ] || d=$([ "$1" = 0 ] && echo 36 || echo 55)
  echo "synth:town:agent=$1,width=480,height=360,fps=10,duration=$d"
}
domain=$((120 + $$ % 50))

agents=3
[ -z "$apart" ] || agents=4
"$app" server --out "$out/server" --agents $agents --dds-domain "$domain" >"$out/server.log" 2>&1 &
server=$!
pids=()
for k in 0 1 2; do
  "$app" agent "$(town $k)" --id $k --quiet --dds-domain "$domain" --out "$out/agent$k" >"$out/agent$k.log" 2>&1 &
  pids+=($!)
done
if [ -n "$apart" ]; then
  "$app" agent "synth:highway:width=480,height=360,fx=360,baseline=0.5,fps=10,duration=$apart" --id 3 --quiet \
    --dds-domain "$domain" --out "$out/agent3" >"$out/agent3.log" 2>&1 &
  pids+=($!)
fi
for p in "${pids[@]}"; do wait "$p"; done
wait "$server"
pids=()
for k in 0 1 2; do
  "$app" run "$(town $k)" --agent $k --quiet >"$out/alone$k.log" 2>&1 &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done

for k in 0 1 2; do
  echo "agent $k"
  grep -E "^(published|time) " "$out/agent$k.log" | sed 's/^/  live   /'
  grep -E "^time " "$out/alone$k.log" | sed 's/^/  no DDS /'
done
echo "server"
grep -E "^(live merge|met|ended|finished|received|agent|loops|final merge|output map|wrote|time) |^ +loop: " "$out/server.log" | sed 's/^/  /'

# Accuracy: each agent's keyframes as it saved them, and as the server's map holds them, each
# aligned alone (SE(3)); then all three agents' keyframes in the server's map under one alignment,
# each one's error under it against its own saved keyframes' (the 1.5x bar of a merged map).
ate() { "$app" eval "$1" "$2" 2>&1 | awk '/ATE \[m\]/ { print $3; exit }'; }
if [ -n "$apart" ]; then
  echo "searches of the run apart (first, last three)"
  grep -E "^ +[0-9]+ run\(s\) apart" "$out/server.log" | sed -n '1p' | sed 's/^ */  /'
  grep -E "^ +[0-9]+ run\(s\) apart" "$out/server.log" | tail -3 | sed 's/^ */  /'
fi
echo "accuracy (keyframe ATE, m)"
pairs=()
for k in 0 1 2; do
  "$app" map export "$out/server/map.fsmap" --trajectory "$out/merged$k.tum" --agent $k >/dev/null
  own[$k]=$(ate "$out/agent$k/keyframes.tum" "$out/agent$k/groundtruth.tum")
  echo "  agent $k: own ${own[$k]}, in the server's map $(ate "$out/merged$k.tum" "$out/agent$k/groundtruth.tum")"
  pairs+=("$out/merged$k.tum" "$out/agent$k/groundtruth.tum")
done
"$app" eval "${pairs[@]}" >"$out/joint.txt"
awk -v o0="${own[0]}" -v o1="${own[1]}" -v o2="${own[2]}" '
  BEGIN { own[1] = o0; own[2] = o1; own[3] = o2 }
  /^estimate/ { for (i = 1; i <= NF; ++i) if ($i == "rmse") { printf "  agent %d in the server'"'"'s map, one alignment for all three: %s (%.2fx its own)\n", $2 - 1, $(i + 1), $(i + 1) / own[$2] } }
  /^all/ { for (i = 1; i <= NF; ++i) if ($i == "rmse") print "  all three, one alignment: " $(i + 1) }' "$out/joint.txt"
