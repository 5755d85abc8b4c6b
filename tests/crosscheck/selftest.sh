#!/bin/sh
# Validates crosscheck.py itself with the Mitsuba-based mock renderer (no pathfarm needed):
#   1. two independent seed sets (Mitsuba seeds and mock seeds) must PASS,
#   2. a 3 % brightened image must FAIL,
#   3. a renderer that does not truncate the pixel filter at the image edge must FAIL.
# Usage: tests/crosscheck/selftest.sh [SCENE.xml]   (default: scenes/cornell-box)
set -u
HERE=$(cd "$(dirname "$0")" && pwd)
SCENE=${1:-$HERE/../../scenes/cornell-box/scene.xml}
MOCK="python3 $HERE/mock_pathfarm.py"
OUT=${TMPDIR:-/tmp}/crosscheck-selftest
status=0
run() {
    mkdir -p "$OUT"
    python3 "$HERE/crosscheck.py" --pathfarm "$MOCK" --scene "$SCENE" "$@" > "$OUT/log.txt" 2>&1
    rc=$?
    tail -4 "$OUT/log.txt"
    return $rc
}

echo "== seed set 1 (expect PASS)"
run --out "$OUT/s1" --seed 1 --mi-seed0 0 || status=1
echo "== seed set 2 (expect PASS)"
run --out "$OUT/s2" --seed 2 --mi-seed0 1000 || status=1
echo "== 3% brighter (expect FAIL)"
if MOCK_SCALE=1.03 run --out "$OUT/bright" --seed 3; then echo "ERROR: brightened image passed"; status=1; fi
echo "== filter not truncated at the border (expect FAIL)"
if MOCK_SAMPLE_BORDER=1 run --out "$OUT/border" --seed 4; then echo "ERROR: border bug passed"; status=1; fi
[ $status -eq 0 ] && echo "selftest OK" || echo "selftest FAILED"
exit $status
