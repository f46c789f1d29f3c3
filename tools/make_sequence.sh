#!/usr/bin/env bash
# Regenerate the sequence fixture fixtures/sequence/cloud.1001.vdb .. cloud.1012.vdb and its
# expected.json (deterministic: no randomness, fixed header UUIDs, so a rerun gives byte-identical
# files). Uses Debian's OpenVDB 10 (python3-openvdb via /usr/bin/python3, vdb_print for a cross-check).
#
#   tools/make_sequence.sh [OUTDIR]     (default: fixtures/sequence)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${1:-$ROOT/fixtures/sequence}"
PY=/usr/bin/python3

source "$ROOT/tools/need_openvdb.sh"
need_openvdb

mkdir -p "$OUT"

"$PY" - "$OUT" <<'PY'
"""Write 12 frames of a small moving, growing soft blob (three overlapping spheres) + expected.json."""
import hashlib
import json
import os
import re
import subprocess
import sys

import numpy as np
import pyopenvdb as vdb

out = sys.argv[1]
FIRST, COUNT = 1001, 12
SHAPE = (48, 32, 32)          # array box [0,47]x[0,31]x[0,31], index == world (voxel size 1)
EDGE = 2.5                    # width (voxels) of the smooth falloff at each sphere's surface
# (offset from the blob centre, radius at frame 0) for the three spheres
SPHERES = [((0.0, 0.0, 0.0), 7.0), ((3.0, 2.0, -1.0), 5.0), ((-3.0, -1.0, 2.0), 4.5)]


def smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def frame_array(t):
    """Density for frame index t (0-based): centre moves +1 voxel/frame along X, radii grow 2%/frame."""
    centre = (14.0 + t, 16.0, 16.0)
    scale = 1.0 + 0.02 * t
    i, j, k = np.meshgrid(*(np.arange(n, dtype=np.float64) for n in SHAPE), indexing="ij")
    empty = np.ones(SHAPE)
    for (ox, oy, oz), r0 in SPHERES:
        r = r0 * scale
        d = np.sqrt((i - centre[0] - ox) ** 2 + (j - centre[1] - oy) ** 2 + (k - centre[2] - oz) ** 2)
        empty *= 1.0 - (1.0 - smoothstep(r - EDGE, r, d))   # soft union: 1 - prod(1 - d_i)
    return (1.0 - empty).astype(np.float32)


def fixed_uuid(filename):
    h = hashlib.sha256(os.path.basename(filename).encode()).hexdigest()[:32]
    return f"{h[0:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:32]}"


def patch_uuid(path):
    """Replace the random header UUID (bytes 21..57) by one derived from the file name."""
    u = fixed_uuid(path).encode("ascii")
    with open(path, "r+b") as f:
        head = f.read(57)
        assert head[:8] == b"\x20\x42\x44\x56\x00\x00\x00\x00", path
        assert int.from_bytes(head[8:12], "little") >= 222, path
        f.seek(21)
        f.write(u)


def vdb_print(path):
    txt = subprocess.run(["vdb_print", "-l", path], check=True, capture_output=True, text=True).stdout
    m = re.search(r"Number of active voxels:\s+([\d,]+)", txt)
    n = int(m.group(1).replace(",", "")) if m else 0
    m = re.search(r"Bounding box of active voxels: \[(-?\d+), (-?\d+), (-?\d+)\] -> "
                  r"\[(-?\d+), (-?\d+), (-?\d+)\]", txt)
    v = [int(x) for x in m.groups()] if m else None
    return n, (v[:3] if v else None), (v[3:] if v else None)


frames, problems = {}, []
for t in range(COUNT):
    name = f"cloud.{FIRST + t}.vdb"
    path = os.path.join(out, name)
    g = vdb.FloatGrid(0.0)
    g.name = "density"
    g.gridClass = vdb.GridClass.FOG_VOLUME
    g.transform = vdb.createLinearTransform(voxelSize=1.0)
    g.copyFromArray(frame_array(t), ijk=(0, 0, 0), tolerance=0.0)   # zeros stay inactive
    g.prune()
    vdb.write(path, grids=[g])
    patch_uuid(path)

    # Facts from the file as written (float64 sums; a tile counts value x voxel count).
    rg = vdb.read(path, "density")
    n, s, lo, hi = 0, 0.0, None, None
    for it in rg.citerOnValues():
        c = int(it.count)
        n += c
        s += float(it.value) * c
        lo = it.value if lo is None else min(lo, it.value)
        hi = it.value if hi is None else max(hi, it.value)
    bmin, bmax = rg.evalActiveVoxelBoundingBox()
    rec = {"active_voxels": n, "min": float(lo), "max": float(hi), "sum": s,
           "bbox_min": list(bmin), "bbox_max": list(bmax)}
    if n != rg.activeVoxelCount():
        problems.append(f"{name}: iterOnValues count {n} != activeVoxelCount {rg.activeVoxelCount()}")
    pn, pmin, pmax = vdb_print(path)
    if (pn, pmin, pmax) != (n, rec["bbox_min"], rec["bbox_max"]):
        problems.append(f"{name}: vdb_print says {pn} {pmin}..{pmax}, pyopenvdb {n} {bmin}..{bmax}")
    frames[name] = rec

with open(os.path.join(out, "expected.json"), "w") as f:
    json.dump({"frames": frames}, f, indent=2)
    f.write("\n")
if problems:
    print("CROSS-CHECK FAILURES:\n  " + "\n  ".join(problems), file=sys.stderr)
    sys.exit(1)
print(f"{out}: {len(frames)} frames + expected.json, cross-checked against vdb_print -l")
PY
