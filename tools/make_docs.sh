#!/usr/bin/env bash
# Renders the README's pictures from committed fixtures into docs/:
#   cloud_sky.png              the set-up command's render: the cloud under the built-in sky
#   cloud_single.png / cloud_multiple.png   single vs multiple scattering (thesis fig. 6.1)
#   *_pathtrace.png            the path tracer's image of the same scenes, to set beside them
#   sun_torus.png / sun_cloud.png           one sun, black sky, single scattering
#   cloud_studio.png / cloud_split.png      one bake relit by two HDRIs (thesis fig. 6.2)
#   torus_studio.png           the two intertwined rings (thesis "torus")
#   orbit.1001.png …           four frames of fixtures/sequence, batch-baked, orbited under the sky
#                              (orbit_pathtrace.*: the path tracer's, same cameras)
# The relit pair comes from one cache: only the environment changes between them.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
OUT=docs
TMP=$(mktemp -d)
trap 'rm -rf "$TMP"' EXIT
# A copy, so a rebuild while the path tracer runs cannot mix two binaries in one set of pictures.
cp target/release/vscatter "$TMP/vscatter"
VS=$TMP/vscatter
RES=640x360
CLOUD=fixtures/cloud.vdb
# Path-tracer samples per pixel: enough that its noise does not hide the shading compared.
SPP=${SPP:-256}

$VS render "$CLOUD" -o "$OUT/cloud_sky.png" --res $RES --quiet
$VS render "$CLOUD" -o "$OUT/cloud_sky_pathtrace.png" --res $RES --method pathtrace --spp "$SPP" --quiet

# Single vs multiple scattering: albedo 0.99, as clouds are; the same camera and environment.
$VS bake "$CLOUD" -o "$TMP/single.vtc" --albedo 0.99 --single-scatter --quiet
$VS bake "$CLOUD" -o "$TMP/multiple.vtc" --albedo 0.99 --quiet
$VS render "$TMP/single.vtc" -o "$OUT/cloud_single.png" --env fixtures/env/sky_sun.exr --res $RES --quiet
$VS render "$TMP/multiple.vtc" -o "$OUT/cloud_multiple.png" --env fixtures/env/sky_sun.exr --res $RES --quiet
for bounces in single:1 multiple:100000; do
    $VS render "$CLOUD" -o "$OUT/cloud_${bounces%%:*}_pathtrace.png" --env fixtures/env/sky_sun.exr --res $RES \
        --albedo 0.99 --method pathtrace --max-bounces "${bounces##*:}" --spp "$SPP" --quiet
done

# One transfer, two environments: relighting needs no new bake.
for env in studio split; do
    $VS render "$TMP/multiple.vtc" -o "$OUT/cloud_$env.png" --env fixtures/env/$env.exr --res $RES --quiet
    $VS render "$CLOUD" -o "$OUT/cloud_${env}_pathtrace.png" --env fixtures/env/$env.exr --res $RES \
        --albedo 0.99 --method pathtrace --spp "$SPP" --quiet
done

$VS render fixtures/torus.vdb -o "$OUT/torus_studio.png" --env fixtures/env/studio.exr --res $RES --quiet
$VS render fixtures/torus.vdb -o "$OUT/torus_studio_pathtrace.png" --env fixtures/env/studio.exr --res $RES \
    --method pathtrace --spp "$SPP" --quiet

# One sun on a black sky, single scattering at the default σt: the shadow volume beside the path
# tracer (docs/accuracy.md, "Suns").
for fx in torus cloud; do
    sun=(fixtures/$fx.vdb --res 480x270 --env sky --env-scale 0 --sun 0.5,0.8,0.3,3,3,3 --exposure 1.5 --quiet)
    $VS render "${sun[@]}" -o "$OUT/sun_$fx.png" --single-scatter
    $VS render "${sun[@]}" -o "$OUT/sun_${fx}_pathtrace.png" --method pathtrace --max-bounces 1 --spp "$SPP"
done
# A sequence: batch, then four frames of a 360° orbit (one a quarter turn), framed alike.
$VS batch 'fixtures/sequence/cloud.####.vdb' --out-dir "$TMP/seq" --quiet
$VS render "$TMP/seq/cloud.####.vtc" --frames 1001-1012:3 --orbit 360 -o "$OUT/orbit.####.png" \
    --res 320x180 --force --quiet
$VS render "$TMP/seq/cloud.####.vtc" --frames 1001-1012:3 --orbit 360 -o "$OUT/orbit_pathtrace.####.png" \
    --res 320x180 --force --quiet --method pathtrace --spp "$SPP"
echo "wrote $OUT/cloud_sky.png, cloud_{single,multiple,studio,split}.png, torus_studio.png and the path tracer's images of each"
