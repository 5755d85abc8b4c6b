#!/usr/bin/env bash
# Makes docs/accuracy/: `pathfarm converge` on the project's scenes and on
# ../shared/scenes/veach-ajar (error against time, noise crops, summaries).
# The charts, crops, CSVs and summaries are kept; the run images and the
# references are not (they are in $OUT/<scene>/ until the next run).
#
#   bench/accuracy.sh [OUT]       (default OUT: target/accuracy; about 25 minutes on 2 cores)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-target/accuracy}
bin=target/release/pathfarm
cargo build --release --quiet
converge() {
    local name=$1 scene=$2
    shift 2
    "$bin" converge "$scene" -o "$out/$name" --budgets 2,4,8 --repeats 3 "$@"
    mkdir -p "docs/accuracy/$name"
    for f in error-vs-time.png error-vs-time.svg crops.png results.csv summary.md; do
        cp "$out/$name/$f" "docs/accuracy/$name/$f"
    done
}
veach=(../shared/scenes/veach-ajar/scene.xml -D resx=320 -D resy=180)
converge veach-ajar "${veach[@]}" --methods path,guided,guided-2017,guided-2019,cluster:2
# The guide's own trade-offs (the same cached reference).
converge veach-ajar-sweep "${veach[@]}" --methods guided \
    --sweep s_tree_threshold=1000,4000 --sweep d_tree_threshold=0.005,0.02
converge door-ajar scenes/door-ajar/scene.xml --methods path,guided,guided-2019
converge caustic scenes/caustic/scene.xml -D resx=128 -D resy=128 --methods path,guided,guided-2019
converge cornell-box scenes/cornell-box/scene.xml -D resx=128 -D resy=128 --methods path,guided,guided-2019
