#!/usr/bin/env bash
# Accuracy report (issue 6): the transfer method against vscatter's path tracer on the cloud and
# torus fixtures, under four environments at two albedos, plus sweeps of the optical depth per
# transfer voxel and of the bake settings. Writes docs/accuracy.md and docs/accuracy/*.png.
# Needs python3 and ImageMagick (`convert`). About an hour on 2 cores at the defaults;
# QUICK=1 tools/accuracy.sh is a two-minute smoke run into target/accuracy/docs/.
# Knobs: RES (96x54), SPP (1024, path tracer), TSPP (16, transfer), ACCURACY_OUT (target/accuracy).
set -euo pipefail
cd "$(dirname "$0")/.."
exec python3 tools/accuracy.py "$@"
