#!/usr/bin/env bash
# Suns against the path tracer (docs/accuracy.md, "Suns"): prints markdown tables of relative RMSE
# (reference noise subtracted, two path-tracer seeds) and bias over the volume's pixels.
#   1. one sun, black environment, single scattering: transfer --single-scatter against the path
#      tracer at --max-bounces 1, cloud and torus, 0.5 and 1 optical depth per density voxel; at
#      the default 1 sample per pixel and at the reference's pixel filter (--spp 64), and pixel by
#      pixel against references of PIXEL_SPP samples (their own seed-to-seed figure is the floor);
#   2. the built-in sky and sky_sun.exr, albedo 0.9, ≈ 0.45 optical depth per transfer voxel and
#      the default σt 1: single and multiple, with the sun as a light and as pixels of the map
#      (--no-extract-sun, the SH transfer alone);
#   3. the path tracer under sky_sun.exr with and without the sun taken out of the map.
# Knobs: RES (256x144), SPP (path tracer, 256), PIXEL_SPP (path tracer of part 1, 8192), OUT
# (target/sun-accuracy), VS (a built binary). About 80 minutes on 2 cores.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${VS:-}" ]; then cargo build --release --quiet; VS=$PWD/target/release/vscatter; fi
RES=${RES:-256x144}
SPP=${SPP:-256}
PIXEL_SPP=${PIXEL_SPP:-8192}
# The transfer's samples per pixel where it is measured at the reference's pixel filter: one
# sample takes the pixel's centre, so at a silhouette or a shadow edge it is not the pixel's mean.
MATCHED_SPP=64
OUT=${OUT:-target/sun-accuracy}
mkdir -p "$OUT"
F=$PWD/fixtures

# compare IMAGE REF1 REF2 → "rmse % | bias %"
cmp() {
    "$VS" compare "$1" "$2" --reference2 "$3" --json |
        python3 -c 'import json,sys; j=json.load(sys.stdin); print("%.1f %% | %+.1f %%" % (100*j["relative_rmse"], 100*j["relative_bias"]))'
}
# pixels IMAGE REF1 REF2 → "share within 10 % | 99th percentile" of the lit pixels
pixels() {
    "$VS" compare "$1" "$2" ${3:+--reference2 "$3"} --json |
        python3 -c 'import json,sys; j=json.load(sys.stdin); print("%.1f %% | %.0f %%" % (100*j["lit_within_tolerance"], 100*j["lit_p99_difference"]))'
}
# pt NAME ARGS… → renders NAME.s1.exr and NAME.s2.exr with the path tracer at $PT_SPP (default
# $SPP) samples per pixel (kept across runs)
pt() {
    local name=$1; shift
    for seed in 1 2; do
        [ -f "$OUT/$name.s$seed.exr" ] ||
            "$VS" render "$@" -o "$OUT/$name.s$seed.exr" --method pathtrace --spp "${PT_SPP:-$SPP}" --seed "$seed" --quiet 2>/dev/null
    done
}

echo "### One sun, black environment: single scattering"
echo
echo "Relative RMSE and bias at 1 sample per pixel (the default) and at $MATCHED_SPP; lit pixels within 10 % and the 99th percentile of their difference at $MATCHED_SPP, against path tracer references of $PIXEL_SPP samples per pixel (floor: one reference seed against the other)."
echo
echo "| fixture | σt (optical depth per voxel) | 1 spp: RMSE | bias | $MATCHED_SPP spp: RMSE | bias | within 10 % | 99th percentile | floor: within 10 % | 99th percentile |"
echo "|---|---|---|---|---|---|---|---|---|---|"
for fx in cloud torus; do for st in 0.5 1; do
    common=("$F/$fx.vdb" --res "$RES" --env sky --env-scale 0 --sun 0.5,0.8,0.3,3,3,3 --no-background --sigma-t "$st")
    name="sun1_${fx}_$st"
    PT_SPP=$PIXEL_SPP pt "$name" "${common[@]}" --max-bounces 1
    "$VS" render "${common[@]}" --single-scatter -o "$OUT/$name.t.exr" --quiet 2>/dev/null
    "$VS" render "${common[@]}" --single-scatter --spp "$MATCHED_SPP" -o "$OUT/$name.t$MATCHED_SPP.exr" --quiet 2>/dev/null
    refs=("$OUT/$name.s1.exr" "$OUT/$name.s2.exr")
    echo "| $fx | $st | $(cmp "$OUT/$name.t.exr" "${refs[@]}") | $(cmp "$OUT/$name.t$MATCHED_SPP.exr" "${refs[@]}") | $(pixels "$OUT/$name.t$MATCHED_SPP.exr" "${refs[@]}") | $(pixels "${refs[@]}") |"
done; done
echo
echo "### Sky with a sun, albedo 0.9: the sun as a light, and as pixels of the map (SH alone)"
echo
echo "| fixture | environment | σt | single, sun as light: RMSE | bias | single, SH alone: RMSE | bias | multiple, sun as light: RMSE | bias | multiple, SH alone: RMSE | bias |"
echo "|---|---|---|---|---|---|---|---|---|---|---|"
for fx in cloud torus; do for env in sky sky_sun; do for st in 0.08 1; do
    e=$([ "$env" = sky ] && echo sky || echo "$F/env/sky_sun.exr")
    common=("$F/$fx.vdb" --res "$RES" --env "$e" --no-background --albedo 0.9 --sigma-t "$st")
    tag="sky_${fx}_${env}_$st"
    pt "$tag.single" "${common[@]}" --max-bounces 1
    pt "$tag.multiple" "${common[@]}"
    row="| $fx | $env | $st"
    for mode in single multiple; do
        for sun in light map; do
            flags=(); [ "$mode" = single ] && flags+=(--single-scatter); [ "$sun" = map ] && flags+=(--no-extract-sun)
            "$VS" render "${common[@]}" "${flags[@]}" -o "$OUT/$tag.$mode.$sun.exr" --quiet 2>/dev/null
        done
    done
    for mode in single multiple; do for sun in light map; do
        row="$row | $(cmp "$OUT/$tag.$mode.$sun.exr" "$OUT/$tag.$mode.s1.exr" "$OUT/$tag.$mode.s2.exr")"
    done; done
    echo "$row |"
done; done; done

echo
echo "### The path tracer with and without the sun taken out of sky_sun.exr (cloud, σt 1, albedo 0.9)"
echo
common=("$F/cloud.vdb" --res "$RES" --env "$F/env/sky_sun.exr" --no-background --albedo 0.9 --sigma-t 1)
pt extract_no "${common[@]}" --no-extract-sun
echo "| comparison | relative RMSE | bias |"
echo "|---|---|---|"
echo "| extracted (seed 1) against the map's sun (seeds 1, 2) | $(cmp "$OUT/sky_cloud_sky_sun_1.multiple.s1.exr" "$OUT/extract_no.s1.exr" "$OUT/extract_no.s2.exr") |"
