#!/usr/bin/env bash
# Batch throughput: the six inputs of the batch bar run one after another with `flatslam run`,
# then as one `flatslam batch`; prints wall time, CPU time, cores kept busy and each sequence's
# ATE both ways. With `many N`, also N short synthetic sequences (synth:room:duration=5,seed=K)
# in one deterministic batch, each trajectory compared with its own deterministic single run.
# usage: bench/batch_bench.sh [BUILD_DIR] [DATASETS_DIR] [many N]
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
datasets="${2:-$here/../shared/datasets}"
app="$build/apps/flatslam"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

inputs=(
  "kitti06|$datasets/kitti/sequences/06|stereo"
  "kitti07|$datasets/kitti/sequences/07|mono"
  "room|synth:room:duration=30|stereo"
  "street|synth:street:duration=30|stereo"
  "room_rgbd|synth:room:duration=30|rgbd"
  "corridor|synth:corridor:duration=30|stereo"
)

# CPU seconds (user + system) of the children that ended so far.
cpu_now() { awk '{print $14 + $15 + $16 + $17}' /proc/$$/stat | awk -v hz="$(getconf CLK_TCK)" '{print $1 / hz}'; }

if [ "${3:-}" != "many-only" ]; then
  : >"$work/manifest.txt"
  cpu0=$(cpu_now)
  t0=$(date +%s.%N)
  printf "%-10s %10s %10s\n" sequence single_ATE batch_ATE >"$work/ate.txt"
  for entry in "${inputs[@]}"; do
    IFS='|' read -r name spec sensor <<<"$entry"
    "$app" run "$spec" --sensor "$sensor" --quiet --out "$work/single/$name" >"$work/single_$name.txt"
    echo "$spec --sensor $sensor --name $name" >>"$work/manifest.txt"
  done
  t1=$(date +%s.%N)
  cpu1=$(cpu_now)
  "$app" batch "$work/manifest.txt" --quiet --out "$work/batch" >"$work/batch.txt"
  t2=$(date +%s.%N)
  cpu2=$(cpu_now)
  cores=$(nproc)
  awk -v w="$(echo "$t1 - $t0" | bc)" -v c="$(echo "$cpu1 - $cpu0" | bc)" -v n="$cores" \
    'BEGIN{printf "one after another: %.1f s wall, %.1f s CPU, %.2f of %d cores busy (%.0f%%)\n", w, c, c/w, n, 100*c/(w*n)}'
  awk -v w="$(echo "$t2 - $t1" | bc)" -v c="$(echo "$cpu2 - $cpu1" | bc)" -v n="$cores" \
    'BEGIN{printf "batch:             %.1f s wall, %.1f s CPU, %.2f of %d cores busy (%.0f%%)\n", w, c, c/w, n, 100*c/(w*n)}'
  grep -E "^(cpu|peak RSS)" "$work/batch.txt"
  for entry in "${inputs[@]}"; do
    IFS='|' read -r name spec sensor <<<"$entry"
    # Monocular: Sim(3) ATE; others SE(3).
    col=$([ "$sensor" = mono ] && echo ate_sim3_m || echo ate_se3_m)
    # The single run's summary line: "ATE  X m RMSE after SE(3) (...); Sim(3) Y m, scale Z".
    if [ "$sensor" = mono ]; then
      single=$(awk '/^ATE/{for(i=1;i<=NF;i++) if($i=="Sim(3)") {print $(i+1); exit}}' "$work/single_$name.txt")
    else
      single=$(awk '/^ATE/{print $2}' "$work/single_$name.txt")
    fi
    batch=$(awk -F, -v c="$col" -v s="$name" 'NR==1{for(i=1;i<=NF;i++) {if($i==c) k=i; if($i=="sequence") q=i}} NR>1 && $q==s {print $k}' "$work/batch/results.csv")
    printf "%-10s %10s %10s  (%s)\n" "$name" "$single" "$batch" "$col" >>"$work/ate.txt"
  done
  cat "$work/ate.txt"
  sed -n '/^| sequence/,/^| summary/p' "$work/batch.txt"
fi

if [ "${3:-}" = "many" ] || [ "${3:-}" = "many-only" ]; then
  n="${4:-100}"
  args=()
  for k in $(seq 1 "$n"); do args+=("synth:room:duration=5,seed=$k"); done
  t0=$(date +%s.%N)
  "$app" batch "${args[@]}" --deterministic --quiet --out "$work/many" >"$work/many.txt"
  t1=$(date +%s.%N)
  echo "many: $n sequences in $(echo "$t1 - $t0" | bc) s"
  grep -E "^(cpu|peak RSS)|summary" "$work/many.txt"
  same=0
  differ=0
  for k in $(seq 1 "$n"); do
    name="synth_room_duration=5_seed=$k"
    "$app" run "synth:room:duration=5,seed=$k" --deterministic --quiet --out "$work/one" >/dev/null
    if cmp -s "$work/one/trajectory.tum" "$work/many/$name/trajectory.tum"; then
      same=$((same + 1))
    else
      differ=$((differ + 1))
      echo "differs: $name"
    fi
  done
  echo "many: $same of $n trajectories equal their single deterministic run ($differ differ)"
fi
