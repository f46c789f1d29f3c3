#!/usr/bin/env bash
# Renders and bakes a fixed set of scenes with two vscatter binaries and says whether every output
# is byte-identical: the check that a refactoring changed no picture and no cache.
#   tools/same_outputs.sh OLD_BINARY NEW_BINARY
# Explicit cameras throughout (automatic framing may change on purpose); the transfer and the path
# tracer, caches, environment turn, scale and window, no background, a double-precision real file.
set -euo pipefail
[ $# -eq 2 ] || { echo "usage: $0 OLD_BINARY NEW_BINARY" >&2; exit 2; }
F="$(cd "$(dirname "$0")/.." && pwd)/fixtures"
OUT=$(mktemp -d)
trap 'rm -rf "$OUT"' EXIT
run_set() {
    local vs="$1" dir="$2"
    mkdir -p "$dir" && cd "$dir"
    local cam=(--camera-pos 40,60,220 --lookat 40,30,40) res=(--res 320x180)
    "$vs" render "$F/cloud.vdb" -o sky.exr "${res[@]}" "${cam[@]}" --quiet
    "$vs" bake "$F/cloud.vdb" -o single.vtc --albedo 0.99 --single-scatter --quiet
    "$vs" bake "$F/cloud.vdb" -o multiple.vtc --albedo 0.99 --quiet
    "$vs" render single.vtc -o single.exr --env "$F/env/sky_sun.exr" "${res[@]}" "${cam[@]}" --quiet
    "$vs" render multiple.vtc -o multiple.exr --env "$F/env/sky_sun.exr" "${res[@]}" "${cam[@]}" --quiet
    "$vs" render multiple.vtc -o studio.exr --env "$F/env/studio.exr" "${res[@]}" "${cam[@]}" --quiet \
        --env-rotate 30 --env-scale 1.5
    "$vs" render multiple.vtc -o split_nobg.exr --env "$F/env/split.exr" "${res[@]}" "${cam[@]}" --quiet \
        --no-background --window hamming
    local tcam=(--camera-pos 50,90,200 --lookat 46,34,34)
    "$vs" render "$F/torus.vdb" -o torus.exr --env "$F/env/studio.exr" "${res[@]}" "${tcam[@]}" --quiet --sigma-t 0.1
    "$vs" render "$F/torus.vdb" -o torus_pt.exr --env "$F/env/studio.exr" --res 96x54 "${tcam[@]}" --quiet \
        --sigma-t 0.1 --method pathtrace --spp 16
    "$vs" render "$F/smoke_double_openvdb7.vdb" -o smoke.exr --res 160x90 --camera-pos 0,30,200 \
        --lookat 0,30,30 --quiet --sigma-t 0.2 --scale 8 --samples 64
    "$vs" bake "$F/multi.vdb" -o multi.vtc --quiet --samples 64
}
(run_set "$(realpath "$1")" "$OUT/old") 2>/dev/null
(run_set "$(realpath "$2")" "$OUT/new") 2>/dev/null
differ=0
for f in "$OUT"/old/*; do
    b=$(basename "$f")
    if cmp -s "$f" "$OUT/new/$b"; then echo "same    $b"; else echo "DIFFERS $b"; differ=1; fi
done
exit $differ
