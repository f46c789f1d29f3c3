#!/usr/bin/env bash
# Soft light on thick media, single scattering (docs/accuracy.md, "Soft light: the fit"): the torus
# at 1.92 optical depths per transfer voxel and the cloud at the default σt, under studio.exr,
# rendered by the transfer (--single-scatter) and by the path tracer (--max-bounces 1), 384×216:
#   docs/soft_fit_{torus,cloud}.png             this build
#   docs/soft_fit_{torus,cloud}_pathtrace.png   the path tracer, SPP samples per pixel (1024)
#   docs/soft_fit_{torus,cloud}_before.png      only with BEFORE=<a vscatter binary> (an earlier build)
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
VS=target/release/vscatter
SPP=${SPP:-1024}
for scene in "torus 0.368" "cloud 1"; do
    read -r fx sigma <<<"$scene"
    args=(fixtures/$fx.vdb --res 384x216 --env fixtures/env/studio.exr --albedo 0.9 --sigma-t "$sigma" --quiet)
    "$VS" render "${args[@]}" --single-scatter -o "docs/soft_fit_$fx.png"
    "$VS" render "${args[@]}" --method pathtrace --max-bounces 1 --spp "$SPP" -o "docs/soft_fit_${fx}_pathtrace.png"
    if [ -n "${BEFORE:-}" ]; then
        "$BEFORE" render "${args[@]}" --single-scatter -o "docs/soft_fit_${fx}_before.png"
    fi
done
