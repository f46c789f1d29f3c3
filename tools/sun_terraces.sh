#!/usr/bin/env bash
# The sunlit left lobe of the cloud fixture, close up (docs/accuracy.md, "Terraces on a sunlit
# lobe"): one sun on a black sky, the transfer against the path tracer.
#   1. pictures: single scattering, transfer and path tracer (docs/sun_terraces*.png);
#   2. single scattering: relative RMSE and bias (reference noise subtracted);
#   3. single + multiple at K = 6 (the default), 3 and 2, against the path tracer's all bounces.
# Knobs: SPP (path tracer, 256), OUT (target/sun-terraces), VS (a built binary). About 10 minutes
# on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${VS:-}" ]; then cargo build --release --quiet; VS=$PWD/target/release/vscatter; fi
SPP=${SPP:-256}
OUT=${OUT:-target/sun-terraces}
mkdir -p "$OUT"
CLOUD=fixtures/cloud.vdb
# The default framing's left lobe at a sixth of its field of view; the sun from upper right front.
view=(--camera-pos 47.5,38.5,241.8 --lookat 28.7,39.7,60.5 --fov 16.2 --env sky --env-scale 0
    --sun 0.5,0.8,0.3,7,7,7 --quiet)

# compare IMAGE REF1 REF2 → "rmse % | bias %"
cmp() {
    "$VS" compare "$1" "$2" --reference2 "$3" --json |
        python3 -c 'import json,sys; j=json.load(sys.stdin); print("%.1f %% | %+.1f %%" % (100*j["relative_rmse"], 100*j["relative_bias"]))'
}

"$VS" render "$CLOUD" "${view[@]}" --res 660x510 --single-scatter -o docs/sun_terraces.png 2>/dev/null
"$VS" render "$CLOUD" "${view[@]}" --res 660x510 --method pathtrace --max-bounces 1 --spp "$SPP" \
    -o docs/sun_terraces_pathtrace.png

for seed in 1 2; do
    for b in 1 100000; do
        [ -f "$OUT/pt_$b.s$seed.exr" ] || "$VS" render "$CLOUD" "${view[@]}" --res 330x255 --no-background \
            --method pathtrace --max-bounces "$b" --spp "$SPP" --seed "$seed" -o "$OUT/pt_$b.s$seed.exr"
    done
done
"$VS" render "$CLOUD" "${view[@]}" --res 330x255 --no-background --single-scatter -o "$OUT/single.exr" 2>/dev/null
echo "| what | relative RMSE | bias |"
echo "|---|---|---|"
echo "| single scattering, K = 6 | $(cmp "$OUT/single.exr" "$OUT/pt_1.s1.exr" "$OUT/pt_1.s2.exr") |"
for k in 6 3 2; do
    "$VS" bake "$CLOUD" --scale "$k" -o "$OUT/k$k.vtc" --quiet 2>/dev/null
    "$VS" render "$OUT/k$k.vtc" "${view[@]}" --res 330x255 --no-background -o "$OUT/k$k.exr" 2>/dev/null
    echo "| single + multiple, K = $k | $(cmp "$OUT/k$k.exr" "$OUT/pt_100000.s1.exr" "$OUT/pt_100000.s2.exr") |"
done
