#!/usr/bin/env bash
# Issue 13's energy check (docs/accuracy.md, "Suns"): albedo 1, one sun from (0.3, 0.9, 0.2), off
# every lattice direction, on a black sky; the transfer against the path tracer, the mean over the
# volume's pixels (bias) and the relative RMSE, the path tracer's noise subtracted. Scenes: the
# fog sphere and the cloud fixtures (the default camera), and a wide slab of 120 × 30 × 120 voxels
# of density 1 seen from straight above (its face on an axis plane, the lattice's hardest case),
# each at σt 1 and 0.2. The slab is written with Debian's OpenVDB (installed when missing).
# Extra arguments go to every transfer render.
# Knobs: SPP (path tracer, 1024 × 2 seeds), RES (128x72), OUT (target/energy), VS (a built binary).
# About 25 minutes on 2 cores, most of it the path tracer, whose images are kept and reused.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ -z "${VS:-}" ]; then cargo build --release --quiet; VS=$PWD/target/release/vscatter; fi
SPP=${SPP:-1024}
RES=${RES:-128x72}
OUT=${OUT:-target/energy}
mkdir -p "$OUT"
SLAB=$OUT/slab.vdb
if [ ! -f "$SLAB" ]; then
    # shellcheck source=tools/need_openvdb.sh
    . tools/need_openvdb.sh
    need_openvdb
    /usr/bin/python3 - "$SLAB" <<'EOF'
import sys
sys.path.insert(0, "tools")
import pyopenvdb as vdb
from vdbgen import block_grid
vdb.write(sys.argv[1], grids=[block_grid((0, 0, 0), (119, 29, 119), 1.0)])
EOF
fi
light=(--res "$RES" --env sky --env-scale 0 --sun 0.3,0.9,0.2 --no-background --albedo 1 --quiet)
above=(--camera-pos 60,200,60 --lookat 60,15,60 --up 0,0,-1)

# scene NAME VDB SIGMA_T [CAMERA...] → a table row
scene() {
    local name=$1 vdb=$2 st=$3
    shift 3
    local pt=$OUT/pt_${name}_$st
    for seed in 1 2; do
        [ -f "$pt.s$seed.exr" ] || "$VS" render "$vdb" "${light[@]}" "$@" --sigma-t "$st" \
            --method pathtrace --spp "$SPP" --seed "$seed" -o "$pt.s$seed.exr"
    done
    "$VS" render "$vdb" "${light[@]}" "$@" --sigma-t "$st" "${EXTRA[@]}" -o "$OUT/$name.exr" 2>/dev/null
    "$VS" compare "$OUT/$name.exr" "$pt.s1.exr" --reference2 "$pt.s2.exr" --json |
        python3 -c 'import json,sys; j=json.load(sys.stdin); print("| '"$name"' | '"$st"' | %+.1f %% | %.1f %% |" % (100*j["relative_bias"], 100*j["relative_rmse"]))'
}

EXTRA=("$@")
echo "| volume | σt | mean (bias) | relative RMSE |"
echo "|---|---|---|---|"
for st in 1 0.2; do
    scene sphere fixtures/sphere_fog.vdb "$st"
    scene cloud fixtures/cloud.vdb "$st"
    scene slab "$SLAB" "$st" "${above[@]}"
done
