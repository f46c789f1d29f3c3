#!/usr/bin/python3
"""Fixture generator for vscatter (run by tools/make_fixtures.sh with /usr/bin/python3).

  make_fixtures.py gen DIR        write the pyopenvdb-made fixtures into DIR
  make_fixtures.py finalize DIR   patch header UUIDs, cross-check with vdb_print -l, write expected.json
  make_fixtures.py reclass SRC DST copy SRC's grids into DST with grid class "unknown"
  make_fixtures.py inspect FILE.. print per-grid compression flags and transform map type (from the bytes)
"""
import json
import os
import re
import struct
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import numpy as np  # noqa: E402
import pyopenvdb as vdb  # noqa: E402
import vdbgen as G  # noqa: E402

# Every fixture (also the vdb_tool-made ones) in the order they appear in expected.json.
FIXTURES = [
    "sphere_ls.vdb", "sphere_fog.vdb", "cloud.vdb", "torus.vdb", "block_tiles.vdb",
    "small_cloud.vdb", "small_cloud_zip.vdb", "small_cloud_half.vdb", "small_cloud_raw.vdb",
    "multi.vdb", "empty.vdb", "vec3_only.vdb",
]

SMALL_CLOUD_VOXEL = 0.05
SMALL_CLOUD_TRANSLATION = (1.0, -0.5, 2.0)


def write(path, grids):
    vdb.write(path, grids=grids)


def gen(out):
    os.makedirs(out, exist_ok=True)
    p = lambda n: os.path.join(out, n)  # noqa: E731

    # cloud.vdb: 96 x 80 x 120 box, cumulus puffs eroded by fBm (seed 1234), voxel size 1
    cloud = G.cumulus_grid((96, 80, 120), seed=1234, base_period=24)
    write(p("cloud.vdb"), [cloud])

    # torus.vdb: two intertwined rings, R = 24, r = 7, in a 92 x 68 x 68 box
    write(p("torus.vdb"), [G.rings_grid((92, 68, 68), R=24, r=7)])

    # block_tiles.vdb: uniform 0.5 over [0,135]^3 -> one 128^3 tile + 817 8^3 tiles, no leaves
    write(p("block_tiles.vdb"), [G.block_grid((0, 0, 0), (135, 135, 135), 0.5)])

    # small_cloud.vdb: 48^3 cumulus, voxel size 0.05, translated
    sc = G.cumulus_grid((48, 48, 48), seed=4321, base_period=14, octaves=4)
    sc.transform = vdb.createLinearTransform(voxelSize=SMALL_CLOUD_VOXEL)
    sc.transform.translate(SMALL_CLOUD_TRANSLATION)
    write(p("small_cloud.vdb"), [sc])

    # multi.vdb: float "temperature", Vec3S "vel", float "density", in that order
    temp = G.rings_grid((48, 40, 40), R=10, r=4)
    temp.name = "temperature"
    temp.gridClass = vdb.GridClass.UNKNOWN
    # temperature: 300 K + 200 K * ring density (values in [300, 500] where active)
    temp.mapOn(lambda v: 300.0 + 200.0 * v)
    vel = vdb.Vec3SGrid((0.0, 0.0, 0.0))
    vel.name = "vel"
    vel.vectorType = vdb.VectorType.CONTRAVARIANT_RELATIVE
    n = 24
    ii, jj, kk = np.meshgrid(np.arange(n), np.arange(n), np.arange(n), indexing="ij")
    c = (n - 1) / 2.0
    # swirl around +Y with a small updraft, zero outside a radius-10 cylinder
    rx, rz = (ii - c), (kk - c)
    inside = (rx ** 2 + rz ** 2) <= 100.0
    v = np.stack([-rz * 0.1, np.full_like(rx, 0.25, dtype=np.float64), rx * 0.1], axis=-1)
    v[~inside] = 0.0
    vel.copyFromArray(v.astype(np.float32), ijk=(4, 4, 4), tolerance=(0.0, 0.0, 0.0))
    dens = G.cumulus_grid((32, 32, 32), seed=99, base_period=12, octaves=3)
    write(p("multi.vdb"), [temp, vel, dens])

    # empty.vdb: one float grid "density" with no active voxels
    write(p("empty.vdb"), [G.fog_grid("density")])

    # vec3_only.vdb: only a Vec3S grid (no scalar grid to render)
    v3 = vdb.Vec3SGrid((0.0, 0.0, 0.0))
    v3.name = "vel"
    v3.fill((0, 0, 0), (15, 15, 15), (1.0, 0.0, 0.0), active=True)
    v3.fill((16, 0, 0), (19, 3, 3), (0.0, 2.0, 0.0), active=True)
    write(p("vec3_only.vdb"), [v3])


# ---------------------------------------------------------------------------
# Byte-level inspection (docs/vdb-format.md: header, descriptors, grid body, transforms):
# compression flags and map type per grid
# ---------------------------------------------------------------------------

class Cur:
    def __init__(self, b, pos=0):
        self.b, self.pos = b, pos

    def take(self, n):
        s = self.b[self.pos:self.pos + n]
        assert len(s) == n, "truncated"
        self.pos += n
        return s

    def u32(self):
        return struct.unpack("<I", self.take(4))[0]

    def i32(self):
        return struct.unpack("<i", self.take(4))[0]

    def i64(self):
        return struct.unpack("<q", self.take(8))[0]

    def string(self):
        return self.take(self.u32()).decode("utf-8", "replace")

    def metamap(self):
        m = {}
        for _ in range(self.u32()):
            name = self.string()
            typ = self.string()
            size = self.u32()
            m[name] = (typ, self.take(size))
        return m


def inspect_bytes(path):
    b = open(path, "rb").read()
    c = Cur(b)
    assert c.take(8) == b"\x20\x42\x44\x56\x00\x00\x00\x00"
    fmt, major, minor = c.u32(), c.u32(), c.u32()
    offsets = c.take(1)[0]
    uuid = c.take(36).decode("ascii")
    c.metamap()
    info = {"format": fmt, "library": f"{major}.{minor}", "has_offsets": offsets, "uuid": uuid, "grids": []}
    for _ in range(c.i32()):
        uname = c.string()
        gtype = c.string()
        parent = c.string()
        gpos, bpos, epos = c.i64(), c.i64(), c.i64()
        g = Cur(b, gpos)
        flags = g.u32()
        meta = g.metamap()
        mapname = g.string()
        half = meta.get("is_saved_as_half_float", ("bool", b"\x00"))[1] == b"\x01"
        info["grids"].append({"name": uname, "type": gtype, "parent": parent, "compression": flags,
                              "map": mapname, "half": half,
                              "file_compression": meta.get("file_compression", ("", b""))[1].decode()})
        c.pos = epos
    return info


# ---------------------------------------------------------------------------
# expected.json
# ---------------------------------------------------------------------------

CLASS_NAMES = {
    vdb.GridClass.FOG_VOLUME: "fog volume",
    vdb.GridClass.LEVEL_SET: "level set",
    vdb.GridClass.UNKNOWN: "unknown",
}


def grid_stats(grid):
    is_vec = grid.valueTypeName.startswith("vec")
    active = tiles = 0
    vsum = 0.0
    vmin = vmax = None
    for it in grid.iterOnValues():
        cnt = it.count
        active += cnt
        if it.depth < 3:       # root (0), internal-5 (1), internal-4 (2) tiles
            tiles += 1
            assert cnt > 1
        else:
            assert cnt == 1
        if not is_vec:
            val = float(it.value)
            vsum += val * cnt
            vmin = val if vmin is None else min(vmin, val)
            vmax = val if vmax is None else max(vmax, val)
    t = grid.transform
    vs = [float(x) for x in t.voxelSize()]
    tr = [float(x) for x in t.indexToWorld((0, 0, 0))]
    if active:
        lo, hi = grid.evalActiveVoxelBoundingBox()
        bbox_min, bbox_max = list(lo), list(hi)
    else:
        bbox_min = bbox_max = None
    assert active == grid.activeVoxelCount(), (grid.name, active, grid.activeVoxelCount())
    bg = grid.background
    return {
        "name": grid.name,
        "value_type": grid.valueTypeName,
        "class": CLASS_NAMES.get(grid.gridClass, str(grid.gridClass)),
        "active_voxels": active,
        "tiles": tiles,
        "leaves": grid.leafCount(),
        "bbox_min": bbox_min,
        "bbox_max": bbox_max,
        "voxel_size": vs,
        "translation": tr,
        "background": [float(x) for x in bg] if is_vec else float(bg),
        "value_sum": None if is_vec else vsum,
        "value_min": None if (is_vec or not active) else vmin,
        "value_max": None if (is_vec or not active) else vmax,
    }


def parse_vdb_print(path):
    """Parse `vdb_print -l` into a list of per-grid dicts."""
    out = subprocess.run(["vdb_print", "-l", path], check=True, capture_output=True, text=True).stdout
    grids = []
    for block in re.split(r"\n(?=Name: )", out):
        m = re.search(r"^Name: (.*)$", block, re.M)
        if not m:
            continue
        g = {"name": m.group(1).strip()}
        m = re.search(r"Leaf\((\d+) x 8\^3\)", block)
        g["leaves"] = int(m.group(1)) if m else None
        m = re.search(r"Internal\((\d+) x 32\^3\), Internal\((\d+) x 16\^3\)", block)
        g["internal5"], g["internal4"] = (int(m.group(1)), int(m.group(2))) if m else (None, None)
        m = re.search(r"Number of active voxels:\s+([\d,]+)", block)
        g["active_voxels"] = int(m.group(1).replace(",", "")) if m else 0
        m = re.search(r"Number of active tiles:\s+([\d,]+)", block)
        g["tiles"] = int(m.group(1).replace(",", "")) if m else 0
        m = re.search(r"Bounding box of active voxels: \[(-?\d+), (-?\d+), (-?\d+)\] -> \[(-?\d+), (-?\d+), (-?\d+)\]",
                      block)
        if m:
            v = [int(x) for x in m.groups()]
            g["bbox_min"], g["bbox_max"] = v[:3], v[3:]
        else:
            g["bbox_min"] = g["bbox_max"] = None
        m = re.search(r"Type: (\S+)", block)
        g["type"] = m.group(1) if m else None
        grids.append(g)
    return grids


def finalize(out):
    files = {}
    problems = []
    for name in FIXTURES:
        path = os.path.join(out, name)
        if not os.path.exists(path):
            problems.append(f"missing {name}")
            continue
        G.patch_uuid(path)
        raw = inspect_bytes(path)
        assert raw["uuid"] == G.fixed_uuid(path)
        grids, _meta = vdb.readAll(path)
        # pyopenvdb.readAll and vdb_print do not keep the file's grid order: use the descriptor order.
        order = [g["name"].split("\x1e")[0] for g in raw["grids"]]
        assert sorted(order) == sorted(g.name for g in grids), (order, [g.name for g in grids])
        grids = sorted(grids, key=lambda g: order.index(g.name))
        stats = [grid_stats(g) for g in grids]
        vp = {g["name"]: g for g in parse_vdb_print(path)}
        if sorted(vp) != sorted(order):
            problems.append(f"{name}: vdb_print lists {sorted(vp)}, file has {order}")
        for s in stats:
            p = vp.get(s["name"])
            if p is None:
                continue
            for key in ("name", "active_voxels", "tiles", "leaves", "bbox_min", "bbox_max"):
                pv = p[key]
                if key == "leaves" and s["active_voxels"] == 0 and pv is None:
                    pv = 0
                if pv is not None and pv != s[key] or (pv is None and s[key] is not None):
                    problems.append(f"{name}/{s['name']}: {key} pyopenvdb={s[key]} vdb_print={pv}")
        files[name] = {"grids": stats}
    doc = {
        "generator": "tools/make_fixtures.sh (OpenVDB %d.%d via pyopenvdb/vdb_print)" % vdb.LIBRARY_VERSION[:2],
        "files": files,
    }
    with open(os.path.join(out, "expected.json"), "w") as f:
        json.dump(doc, f, indent=2, sort_keys=False)
        f.write("\n")
    if problems:
        print("CROSS-CHECK FAILURES:\n  " + "\n  ".join(problems), file=sys.stderr)
        sys.exit(1)
    print(f"expected.json: {len(files)} files, cross-checked against vdb_print -l")


def inspect(paths):
    for path in paths:
        info = inspect_bytes(path)
        for g in info["grids"]:
            print(f"{os.path.basename(path)}: format {info['format']} lib {info['library']} "
                  f"grid {g['name']!r} {g['type']} compression=0x{g['compression']:x} map={g['map']} "
                  f"half={g['half']} ({g['file_compression']})")


if __name__ == "__main__":
    cmd = sys.argv[1]
    if cmd == "gen":
        gen(sys.argv[2])
    elif cmd == "finalize":
        finalize(sys.argv[2])
    elif cmd == "reclass":
        # reclass SRC DST: copy of SRC's grids with class "unknown" (OpenVDB's writer drops ZIP for
        # fog volumes and level sets, so a ZIP-compressed fixture must not be a fog volume).
        grids, meta = vdb.readAll(sys.argv[2])
        for g in grids:
            g.gridClass = vdb.GridClass.UNKNOWN
        vdb.write(sys.argv[3], grids=grids)
    elif cmd == "inspect":
        inspect(sys.argv[2:])
    else:
        sys.exit(__doc__)
