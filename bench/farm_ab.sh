#!/usr/bin/env bash
# Paired whole-job runs of `pathfarm cluster` with two binaries, alternating, on one scene;
# prints each run's wall seconds and the B/A ratio per repetition, and fails if the two
# binaries' images differ (for farm changes meant not to alter a bit; set
# FARM_AB_IMAGES=may-differ for a change of schedule, e.g. pipelined training passes).
#
#   bench/farm_ab.sh A_BINARY B_BINARY [REPS] [-- extra cluster flags]
#
# Default job: ../shared/scenes/veach-ajar at 640x360, guided_path, 32 spp (FARM_AB_SPP),
# seed 1, 2 workers of 1 thread. The machine is noisy: read the median of the paired ratios.
set -euo pipefail
a=$1 b=$2 reps=${3:-3}
shift $(( $# >= 3 ? 3 : 2 ))
[ "${1:-}" = "--" ] && shift
here=$(cd "$(dirname "$0")" && pwd)
scene=$here/../../shared/scenes/veach-ajar/scene.xml
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
flags=(--workers 2 --threads-per-worker 1 --spp "${FARM_AB_SPP:-32}" --seed 1 --resolution 640x360
       -D integrator=guided_path "$@")
run() { # binary name -> wall seconds
    local t0 t1
    t0=$(date +%s.%N)
    "$1" cluster "$scene" -o "$out/$2.exr" "${flags[@]}" >"$out/$2.log" 2>&1 ||
        { cat "$out/$2.log" >&2; exit 1; }
    t1=$(date +%s.%N)
    echo "$t1 - $t0" | bc
}
for r in $(seq 1 "$reps"); do
    if (( r % 2 )); then ta=$(run "$a" a); tb=$(run "$b" b); else tb=$(run "$b" b); ta=$(run "$a" a); fi
    if [ "${FARM_AB_IMAGES:-same}" != may-differ ]; then
        cmp -s "$out/a.exr" "$out/b.exr" || { echo "repetition $r: the images differ" >&2; exit 1; }
    fi
    printf 'rep %d  A %.2f s  B %.2f s  B/A %.3f\n' "$r" "$ta" "$tb" "$(echo "$tb / $ta" | bc -l)"
done
