#!/usr/bin/env bash
# Live agents over DDS on one machine: a map server and three town agents at once (loopback),
# then the same three runs at once without publishing or server. Prints, per agent: keyframes and
# bytes sent (per keyframe and per second), the final map update, and the tracking time with and
# without publishing (both beside the two other agents on the same cores), and the last correction
# the agent received; for the server: each live merge while the agents ran (time, keyframes, maps
# joined), when agents met and how long after their first overlap the merged map was ready, each
# agent's end of run, messages received, the merge and save time after the agents stopped, and
# the output maps.
# usage: bench/agents_bench.sh [BUILD_DIR] [OUT_DIR]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
out="${2:-$(mktemp -d)}"
app="$build/apps/flatslam"
mkdir -p "$out"
town() { echo "synth:town:agent=$1,width=480,height=360,fps=10,duration=$([ "$1" = 0 ] && echo 36 || echo 55)"; }
domain=$((120 + $$ % 50))

"$app" server --out "$out/server" --agents 3 --dds-domain "$domain" >"$out/server.log" 2>&1 &
server=$!
pids=()
for k in 0 1 2; do
  "$app" agent "$(town $k)" --id $k --quiet --dds-domain "$domain" >"$out/agent$k.log" 2>&1 &
  pids+=($!)
done
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
grep -E "^(live merge|met|ended|finished|received|agent|loops|final merge|output map|wrote|time) " "$out/server.log" | sed 's/^/  /'
