#!/usr/bin/env bash
# Accuracy with defaults only: runs `flatslam run` with no tuning flag on every real sequence in
# the shared datasets and on every synthetic scene, and prints one row each: frames, lost frames
# (after initialization), keyframes, ATE after SE(3) (metres and % of path), ATE after Sim(3),
# Sim(3) scale, RPE per frame, frames/s, whether a monocular run started over with the camera its
# map refined (cam: "refit@N", N the frames of the first pass; "end": refined after the last frame,
# in place), and the reference figure or bar
# the row is held to.
# usage: bench/accuracy_table.sh [BUILD_DIR] [DATASETS_DIR] [--quick]
#   --quick: synthetic scenes run 20 s instead of their default duration.
set -euo pipefail
here="$(cd "$(dirname "$0")/.." && pwd)"
build="${1:-$here/build}"
datasets="${2:-$here/../shared/datasets}"
quick="${3:-}"
app="$build/apps/flatslam"
[ -x "$app" ] || { echo "accuracy_table.sh: $app not found (build first)" >&2; exit 1; }
synth_duration=""
[ "$quick" = "--quick" ] && synth_duration=",duration=20"

# name|dataset|sensor|reference (what the row is held to; "-" = none)|extra flags (optional)
runs=(
  "kitti07|$datasets/kitti/sequences/07|mono|Sim(3) ATE <= 0.283 m (ORB-SLAM2: 0.268 m), 0 lost"
  "kitti06|$datasets/kitti/sequences/06|stereo|ATE <= 0.059 m, 0 lost"
  "kitti06 7 frames dropped|$datasets/kitti/sequences/06|stereo|ATE <= 0.059 m, 0 lost|--skip 10:11,20:22,30:31,40:43"
  "kitti07 7 frames dropped|$datasets/kitti/sequences/07|mono|Sim(3) ATE < 0.5% of path, 0 lost|--skip 30:31,60:62,90:91,120:123"
  "kitti06|$datasets/kitti/sequences/06|mono|-"
  "euroc-MH01-f000-149|$datasets/euroc/MH_01_f000_149|stereo|-"
  "euroc-MH01-f000-149|$datasets/euroc/MH_01_f000_149|mono|-"
  "euroc-V101-first20|$datasets/euroc/V1_01_first20|stereo|static: loader check"
  "synth:room|synth:room${synth_duration}|stereo|ATE < 1% of path"
  "synth:room|synth:room${synth_duration}|rgbd|ATE < 1% of path"
  "synth:room|synth:room${synth_duration}|mono|Sim(3) ATE < 2% of path"
  "synth:room:dynamic=0.3|synth:room:dynamic=0.3${synth_duration}|stereo|ATE < 1% of path"
  "synth:corridor|synth:corridor${synth_duration}|stereo|ATE < 1% of path"
  "synth:street|synth:street${synth_duration}|stereo|ATE < 1% of path"
  "synth:highway|synth:highway${synth_duration}|stereo|ATE < 0.5% of path, scale within 1%"
  "synth:highway|synth:highway${synth_duration}|mono|init within 1 s, < 1% lost"
  "synth:highway rig -0.1 px|synth:highway:rig_error=-0.1${synth_duration}|stereo|rig off by KITTI 06's -0.1 px: scale within 2%"
  "synth:handheld|synth:handheld${synth_duration}|stereo|0 lost, ATE < 1% of path"
  "synth:handheld|synth:handheld${synth_duration}|rgbd|0 lost, ATE < 1% of path"
  "synth:handheld|synth:handheld${synth_duration}|mono|init within 1 s, < 1% lost"
  # The same scenes at cameras and frame rates they were not first run at.
  "synth:room 320x240|synth:room:width=320,height=240,fx=260${synth_duration}|rgbd|0 lost, ATE < 1% of path"
  "synth:handheld 10 Hz|synth:handheld:fps=10${synth_duration}|stereo|0 lost, ATE < 1% of path"
  "synth:handheld 10 Hz|synth:handheld:fps=10${synth_duration}|rgbd|0 lost, ATE < 1% of path"
  # Other datasets' cameras on these scenes: EuRoC's (752x480, fx 458, 0.11 m, 20 Hz), TUM RGB-D's
  # (640x480, fx 525, Kinect-class depth), KITTI's (1241x376, fx 718, 0.54 m, 10 Hz), and stereo
  # rigs short for the motorway.
  "synth:handheld EuRoC camera|synth:handheld:width=752,height=480,fx=458,baseline=0.11,fps=20${synth_duration}|stereo|0 lost, ATE < 1% of path"
  "synth:handheld EuRoC camera|synth:handheld:width=752,height=480,fx=458,fps=20${synth_duration}|mono|< 1% lost"
  "synth:handheld TUM camera SL|synth:handheld:fx=525,structured_light=1${synth_duration}|rgbd|0 lost, ATE < 1% of path"
  "synth:handheld TUM camera|synth:handheld:fx=525${synth_duration}|mono|< 1% lost"
  "synth:street KITTI camera|synth:street:width=1241,height=376,fx=718,baseline=0.54,fps=10${synth_duration}|stereo|ATE < 1% of path"
  "synth:street KITTI camera|synth:street:width=1241,height=376,fx=718,fps=10${synth_duration}|mono|Sim(3) ATE < 1% of path"
  # A lens the calibration leaves out (k1 = 0.02 moves KITTI's image edge by about 9 px): the run's
  # camera check refines the model and starts over.
  "synth:street KITTI lens k1|synth:street:width=1226,height=370,fx=707,fps=10,k1=0.02${synth_duration}|mono|Sim(3) ATE < 1% of path"
  "synth:highway 0.25 m rig|synth:highway:baseline=0.25${synth_duration}|stereo|ATE < 0.5% of path, scale within 1%"
  "synth:highway EuRoC camera|synth:highway:width=752,height=480,fx=458,baseline=0.11${synth_duration}|stereo|no bar: its scale is the weakest case"
  "synth:highway EuRoC camera|synth:highway:width=752,height=480,fx=458${synth_duration}|mono|no bar: varies with the seed"
  # Half KITTI's focal length on a 672x376 image with a 0.12 m rig (a small wide stereo camera).
  "synth:highway fx 350 rig|synth:highway:width=672,height=376,fx=350,baseline=0.12${synth_duration}|stereo|no bar: short at this focal length"
  # SL: RGB-D depth as a structured-light (Kinect-class) sensor reads it: quantized, shadowed, fattened, 1 px off.
  "synth:room SL depth|synth:room:structured_light=1${synth_duration}|rgbd|0 lost, ATE < 1% of path"
  "synth:handheld SL depth|synth:handheld:structured_light=1${synth_duration}|rgbd|0 lost, ATE < 1% of path"
)

printf "%-26s %-6s %6s %5s %5s %9s %7s %9s %7s %9s %8s %9s  %s\n" sequence sensor frames lost kfs ATE_m ATE_% ATE_sim3 scale RPE_m fps cam reference
for entry in "${runs[@]}"; do
  IFS='|' read -r name spec sensor reference extra <<<"$entry"
  # --quick on a scene given without options: its ",duration=20" starts the option list.
  [[ "$spec" == synth:* && "${spec#synth:}" != *:* ]] && spec="${spec/,/:}"
  if [[ "$spec" != synth:* && ! -d "$spec" ]]; then
    printf "%-26s %-6s missing: %s\n" "$name" "$sensor" "$spec"
    continue
  fi
  # shellcheck disable=SC2086
  summary=$("$app" run "$spec" --sensor "$sensor" $extra --quiet 2>&1) || true
  frames=$(awk '/^frames/{print $2}' <<<"$summary")
  lost=$(awk '/^frames/{print $4}' <<<"$summary")
  kfs=$(awk '/^map /{print $2}' <<<"$summary")
  fps=$(awk '/^throughput/{print $2}' <<<"$summary")
  ate=$(awk '/^ATE/{print $2}' <<<"$summary")
  pct=$(awk '/^ATE/{gsub(/\(/,"",$0); for(i=1;i<=NF;i++) if($i ~ /%$/) {print $i; exit}}' <<<"$summary")
  scale=$(awk '/^ATE/{print $NF}' <<<"$summary")
  sim3=$(awk '/^ATE/{for(i=1;i<=NF;i++) if($i=="Sim(3)") {print $(i+1); exit}}' <<<"$summary")
  rpe=$(awk '/^RPE/{print $2}' <<<"$summary")
  # "+end": the whole map's check after the last frame refined the camera again (in place).
  cam=$(awk '/^camera check  the map of the first/{c = "refit@" $8} /^ +it disagreed: its/{c = c (c ? "+" : "") "end"}
             END {print c}' <<<"$summary")
  printf "%-26s %-6s %6s %5s %5s %9s %7s %9s %7s %9s %8s %9s  %s\n" "$name" "$sensor" "${frames:--}" "${lost:--}" \
    "${kfs:--}" "${ate:--}" "${pct:--}" "${sim3:--}" "${scale:--}" "${rpe:--}" "${fps:--}" "${cam:--}" "$reference"
done
