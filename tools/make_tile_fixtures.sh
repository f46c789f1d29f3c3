#!/usr/bin/env bash
# Writes the huge-tile fixtures: fog volumes of billions of active voxels stored as a few tiles,
# which every command must answer at once (tests/cli/vdb.rs), with their statistics as OpenVDB
# counts them (fixtures/huge_tiles.json).
#   huge_root_tile.vdb   one root-level tile: [0, 4095]³ at 0.5 (68 719 476 736 voxels)
#   huge_tiles_2048.vdb  a 2048³ box of 4096 128³ tiles at 0.5 (8 589 934 592 voxels)
# Needs Debian's python3-openvdb (installed when missing: tools/need_openvdb.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
source tools/need_openvdb.sh
need_openvdb
/usr/bin/python3 - <<'PY'
import json, sys
sys.path.insert(0, "tools")
import pyopenvdb as vdb
import vdbgen as G

def fog():
    g = vdb.FloatGrid()
    g.name = "density"
    g.gridClass = vdb.GridClass.FOG_VOLUME
    return g

root = fog()
root.fill((0, 0, 0), (4095, 4095, 4095), 0.5, active=True)
box = fog()
for i in range(16):
    for j in range(16):
        for k in range(16):
            o = (128 * i, 128 * j, 128 * k)
            box.fill(o, tuple(c + 127 for c in o), 0.5, active=True)
stats = {}
for name, g in [("huge_root_tile.vdb", root), ("huge_tiles_2048.vdb", box)]:
    path = "fixtures/" + name
    vdb.write(path, grids=[g])
    G.patch_uuid(path)
    lo, hi = g.evalActiveVoxelBoundingBox()
    stats[name] = {"active_voxels": g.activeVoxelCount(), "leaves": g.leafCount(),
                   "bbox_min": list(lo), "bbox_max": list(hi)}
    print(name, stats[name])
with open("fixtures/huge_tiles.json", "w") as f:
    json.dump(stats, f, indent=1)
    f.write("\n")
PY
