#!/usr/bin/env bash
# The compose test: the image built from this checkout, deploy/docker-compose.yml brought up
# (a coordinator and three workers in containers), a shipped scene submitted from the host
# with `pathfarm submit`; one worker container is killed (docker kill) in the middle of a
# training iteration, and the EXR must be byte-identical to `docker run IMAGE render` of the
# same job; then the coordinator container is stopped and started mid-job, and that job too
# must complete byte-identical. Always torn down (docker-compose down -v), even on failure.
#
# Needs the Docker engine and docker-compose (1.29). Without them it skips with a message,
# except with CI=true, where it fails. It prints "compose test: RAN" when it ran.
# Uses the host binary target/release/pathfarm as the client (built by ./test.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."

if ! docker info >/dev/null 2>&1 || ! command -v docker-compose >/dev/null 2>&1; then
    if [ "${CI:-}" = "true" ]; then
        echo "compose test: FAILED: no Docker engine or no docker-compose on this CI machine" >&2
        exit 1
    fi
    echo "compose test: SKIPPED: no Docker engine or no docker-compose here" >&2
    exit 0
fi

host_bin="${PATHFARM_HOST_BIN:-target/release/pathfarm}"
if [ ! -x "${host_bin}" ]; then
    cargo build --release -p pathfarm
fi
image="pathfarm:compose-test"
project="pathfarm-compose-$$"
work="$(mktemp -d)"
free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
export PATHFARM_IMAGE="${image}"
export PATHFARM_TOKEN="$(head -c 16 /dev/urandom | od -An -tx1 | tr -d ' \n')"
export PATHFARM_PORT="$(free_port)"
export PATHFARM_METRICS_PORT="$(free_port)"
url="http://127.0.0.1:${PATHFARM_PORT}"
compose() { docker-compose -p "${project}" -f deploy/docker-compose.yml "$@"; }
teardown() {
    status=$?
    if [ "${status}" != 0 ]; then
        echo "compose test: logs of the stack:" >&2
        compose logs --no-color --tail 60 >&2 || true
    fi
    compose down -v --remove-orphans >/dev/null 2>&1 || true
    rm -rf "${work}"
    exit "${status}"
}
trap teardown EXIT
fail() { echo "compose test: FAILED: $*" >&2; exit 1; }

scene_dir="$(pwd)/scenes/door-ajar"
job=(-D integrator=guided_path -D resx=240 -D resy=136 --spp 64)

echo "compose test: building ${image}" >&2
deploy/build-image.sh "${image}"

reference() { # seed -> writes ${work}/ref-SEED.exr with `docker run IMAGE render`
    docker run --rm -v "${scene_dir}:/scene:ro" -v "${work}:/out" "${image}" \
        render /scene/scene.xml "${job[@]}" --seed "$1" --no-png -o "/out/ref-$1.exr" >/dev/null 2>&1 \
        || fail "docker run ${image} render"
}

pf() { "${host_bin}" "$@"; }
status_field() { # job field -> value from `pathfarm status JOB` (empty while unreachable)
    pf status "$1" --coordinator "${url}" 2>/dev/null | awk -v f="$2:" '$1 == f {print $2}'
}
wait_until() { # seconds description command...
    local deadline=$((SECONDS + $1)) what="$2"; shift 2
    until "$@"; do
        [ "${SECONDS}" -lt "${deadline}" ] || fail "timed out waiting for ${what}"
        sleep 0.2
    done
}
farm_serving() { pf health --coordinator "${url}" >/dev/null 2>&1; }
workers_connected() { [ "$(pf status --coordinator "${url}" 2>/dev/null | grep -c ' connected ')" -ge "$1" ]; }
training_iteration() { # job min -> true once the job trains iteration >= min
    [ "$(status_field "$1" state)" = "training" ] && [ "$(status_field "$1" iteration)" -ge "$2" ]
}
job_done() {
    local s; s="$(status_field "$1" state)"
    [ "${s}" = "failed" ] || [ "${s}" = "cancelled" ] && fail "job $1 ended ${s}"
    [ "${s}" = "done" ]
}
submit() { # seed -> job id
    pf submit "${scene_dir}/scene.xml" "${job[@]}" --seed "$1" --coordinator "${url}" --tile 16
}

echo "compose test: bringing the stack up (project ${project})" >&2
compose up -d >/dev/null 2>&1 || fail "docker-compose up"
wait_until 120 "the farm to serve (grpc.health.v1)" farm_serving
wait_until 60 "three workers" workers_connected 3
reference 3
reference 4

# 1. a worker container killed in the middle of a training iteration
id1="$(submit 3)"
wait_until 120 "job ${id1} to train iteration 2" training_iteration "${id1}" 2
docker kill "${project}_worker-1_1" >/dev/null || fail "docker kill"
[ "$(status_field "${id1}" state)" != "done" ] || fail "job ${id1} finished before the worker was killed"
echo "compose test: killed worker-1 while ${id1} trained iteration $(status_field "${id1}" iteration)" >&2
wait_until 300 "job ${id1}" job_done "${id1}"
pf fetch "${id1}" --coordinator "${url}" -o "${work}/job1.exr" >/dev/null
cmp -s "${work}/job1.exr" "${work}/ref-3.exr" || fail "job ${id1}: the EXR differs from docker run render"

# 2. the coordinator container stopped and started mid-job
id2="$(submit 4)"
wait_until 120 "job ${id2} to train iteration 2" training_iteration "${id2}" 2
compose stop coordinator >/dev/null 2>&1 || fail "stopping the coordinator"
compose start coordinator >/dev/null 2>&1 || fail "starting the coordinator"
echo "compose test: restarted the coordinator while ${id2} was training" >&2
wait_until 300 "job ${id2} after the coordinator restart" job_done "${id2}"
pf fetch "${id2}" --coordinator "${url}" -o "${work}/job2.exr" >/dev/null
cmp -s "${work}/job2.exr" "${work}/ref-4.exr" || fail "job ${id2}: the EXR differs from docker run render"
# the metrics port answers
# (read whole first: `grep -q` ends at its match, and under pipefail the curl still writing
# the rest would fail the pipe)
metrics="$(curl -sf "http://127.0.0.1:${PATHFARM_METRICS_PORT}/metrics")" \
    || fail "the metrics port does not answer"
grep -q '^pathfarm_jobs{state="done"} 2' <<<"${metrics}" \
    || fail "metrics do not report two done jobs: $(grep '^pathfarm_jobs' <<<"${metrics}" | tr '\n' ' ')"

echo "compose test: RAN: image built, stack up, a worker killed mid-iteration and the coordinator restarted mid-job; both EXRs byte-identical to docker run render"
