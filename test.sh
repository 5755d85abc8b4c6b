#!/usr/bin/env bash
# Runs every pathfarm test: unit tests of all crates and the integration tests
# (which include the cross-check against Mitsuba 3). Installs the Python side
# of the cross-check (mitsuba, numpy from PyPI) if it is missing.
set -euo pipefail
cd "$(dirname "$0")"

if ! python3 -c "import mitsuba, numpy" >/dev/null 2>&1; then
    echo "test.sh: installing the Mitsuba 3 cross-check dependencies (pip: mitsuba numpy)" >&2
    python3 -m pip install --quiet --disable-pip-version-check mitsuba numpy
fi

# One build profile for tests and benchmarks: release.
cargo test --release --workspace "$@"

# With test-name arguments, only the cargo tests run.
if [ "$#" -eq 0 ]; then
    # Kubernetes manifests against the API schemas (offline; pip kubernetes-validate).
    tests/k8s/validate.sh
    # The docker-compose farm (builds the image; skips without Docker unless CI=true).
    tests/compose/compose_test.sh
    # The web dashboard in headless Chromium (skips without it unless CI=true).
    tests/browser/run.sh
fi
