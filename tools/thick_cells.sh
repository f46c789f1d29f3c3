#!/usr/bin/env bash
# The default scene (the cloud under the built-in sky, σt 1, albedo 0.9) at 256×144, rendered by
# the transfer and by the path tracer, for docs/accuracy.md ("Thick cells"):
#   docs/thick_cells_after.png       this build
#   docs/thick_cells_pathtrace.png   the path tracer, 256 spp
#   docs/thick_cells_before.png      only with BEFORE=<a vscatter binary> (an earlier build)
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release --quiet
VS=target/release/vscatter
scene=(fixtures/cloud.vdb --res 256x144 --env sky --albedo 0.9 --sigma-t 1 --quiet)
"$VS" render "${scene[@]}" -o docs/thick_cells_after.png
"$VS" render "${scene[@]}" -o docs/thick_cells_pathtrace.png --method pathtrace --spp 256
if [ -n "${BEFORE:-}" ]; then
    "$BEFORE" render "${scene[@]}" -o docs/thick_cells_before.png
fi
