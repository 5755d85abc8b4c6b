#!/usr/bin/env bash
# A very large job and a small one submitted together to a two-worker farm: both must
# finish, the small one while the large one is set up and rendered, and the coordinator
# must keep answering `pathfarm status`.
#
#   bench/farm_big.sh [SIZE] [SPP] [JOB_MEMORY_MB]     (defaults: 4096 4 21000)
#
# Prints each job's wall seconds from its submission, the slowest `pathfarm status` during
# the run, the coordinator's peak resident memory, and how often a worker was declared lost.
# Needs target/release/pathfarm. The default job memory budget (half the machine's memory)
# refuses a 4096x4096 job on a 24 GiB machine: the estimate counts every film a session
# may hold.
set -u
SIZE=${1:-4096}
SPP=${2:-4}
MEM=${3:-21000}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
B=$ROOT/target/release/pathfarm
D=$(mktemp -d /tmp/pathfarm-big-XXXX)
export PATHFARM_TOKEN=big-bench NO_COLOR=1
PORT=$((20000 + RANDOM % 20000))
URL=http://127.0.0.1:$PORT
cleanup() { kill "${PIDS[@]}" 2>/dev/null; wait 2>/dev/null; rm -rf "$D"; }
PIDS=()
trap cleanup EXIT
$B coordinator --listen 127.0.0.1:$PORT --data "$D/c" --job-memory-mb "$MEM" 2> "$D/coord.log" &
PIDS+=($!)
sleep 1
for w in 1 2; do
    $B worker --coordinator $URL --threads 1 --cache "$D/w$w" 2> "$D/w$w.log" &
    PIDS+=($!)
done
sleep 2
S=$ROOT/scenes/cornell-box/scene.xml
submit() { # NAME RES SPP
    local t0
    t0=$(date +%s.%N)
    $B submit "$S" --coordinator $URL -D integrator=guided_path -D resx="$2" -D resy="$2" \
        --spp "$3" --wait -o "$D/$1.exr" 2> "$D/$1.log"
    echo "$1 (${2}x$2, $3 spp): rc=$? after $(echo "$(date +%s.%N) - $t0" | bc) s"
}
submit big "$SIZE" "$SPP" &
BIG=$!
sleep 2
submit small 128 16 &
SMALL=$!
SLOWEST=0
while kill -0 $BIG 2>/dev/null || kill -0 $SMALL 2>/dev/null; do
    s=$( { /usr/bin/time -f %e $B status --coordinator $URL > /dev/null; } 2>&1 | tail -1)
    SLOWEST=$(echo "if ($s > $SLOWEST) $s else $SLOWEST" | bc)
    sleep 1
done
wait $BIG $SMALL
echo "slowest pathfarm status: ${SLOWEST} s"
echo "coordinator peak: $(grep VmHWM /proc/${PIDS[0]}/status | tr -s ' ')"
echo "workers declared lost: $(cat "$D"/w*.log | grep -c 'declared lost')"
