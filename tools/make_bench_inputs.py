#!/usr/bin/python3
"""Generate vscatter's larger benchmark volumes (not committed). Run with /usr/bin/python3.

  make_bench_inputs.py [OUTDIR] [--only NAME[,NAME...]] [--force]

Outputs (cached: an existing file is skipped unless --force):
  torus300.vdb     two intertwined rings in a 300^3 box, major radius 80, tube radius 22
  helix600.vdb     thin smoke helix (tube radius 6) in a ~600^3 mostly empty box, built sparsely
  block300.vdb     uniform 0.5 block over [0,299]^3 via fill -> 128^3 and 8^3 active tiles + leaves
  cloud_large.vdb  ~200 x 170 x 320 cumulus (same generator as fixtures/cloud.vdb)
Production scale, made only when named with --only (minutes and gigabytes of work each):
  cloud_quarter.vdb  ~500 x 340 x 610 cumulus, the size of the public Disney cloud at 1/4
  cloud_half.vdb     ~1000 x 680 x 1220 cumulus, the Disney cloud at 1/2 (>= 150 M active voxels)
Both are built 64 x-slices at a time: no more than a slab of dense noise is held.
  cloud_seq/cloud.1001.vdb ... cloud.1024.vdb
                   24 frames of a 128^3 cumulus drifting +1 voxel in x per frame (batch bench)
All grids are float fog volumes named "density", voxel size 1; header UUIDs are fixed, so the
outputs are deterministic.
"""
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import pyopenvdb as vdb  # noqa: E402
import vdbgen as G  # noqa: E402

BENCH = {
    "torus300.vdb": lambda: G.rings_grid((300, 300, 300), R=80, r=22),
    "helix600.vdb": lambda: G.helix_grid(box=600, helix_radius=180.0, turns=4.0, tube=6.0),
    "block300.vdb": lambda: G.block_grid((0, 0, 0), (299, 299, 299), 0.5),
    "cloud_large.vdb": lambda: G.cumulus_grid((200, 170, 320), seed=2024, base_period=48, octaves=6),
}
SCALE = {
    "cloud_quarter.vdb": lambda: G.cumulus_grid((500, 340, 610), seed=2025, base_period=96, octaves=6),
    "cloud_half.vdb": lambda: G.cumulus_grid((1000, 680, 1220), seed=2025, base_period=192, octaves=7),
}


SEQUENCE_FRAMES = range(1001, 1025)


def make_sequence(out, force):
    """The batch bench's sequence: one 128^3 cumulus written 24 times, shifted a voxel a frame."""
    seq = os.path.join(out, "cloud_seq")
    os.makedirs(seq, exist_ok=True)
    paths = [os.path.join(seq, f"cloud.{n}.vdb") for n in SEQUENCE_FRAMES]
    if all(os.path.exists(p) for p in paths) and not force:
        print("cloud_seq: cached, skipped")
        return
    fbm = G.FBm((128, 128, 128), base_period=40, octaves=5, seed=77)
    a = G.cumulus_box((128, 128, 128), (0, 0, 0), (128, 128, 128), fbm)
    for i, path in enumerate(paths):
        grid = G.fog_grid()
        grid.copyFromArray(a, ijk=(i, 0, 0), tolerance=0.0)
        grid.prune(0.0)
        tmp = path + ".tmp"
        vdb.write(tmp, grids=[grid])
        G.patch_uuid(tmp)
        os.replace(tmp, path)
    print(f"cloud_seq: {len(paths)} frames of {grid.activeVoxelCount():,} active voxels")


def main(argv):
    force = "--force" in argv
    argv = [a for a in argv if a != "--force"]
    only = None
    if "--only" in argv:
        i = argv.index("--only")
        only = set(argv[i + 1].split(","))
        del argv[i:i + 2]
    out = argv[0] if argv else "target/bench-inputs"
    os.makedirs(out, exist_ok=True)
    if not only or "cloud_seq" in only:
        make_sequence(out, force)
    wanted = dict(BENCH)
    wanted.update({n: m for n, m in SCALE.items() if only and (n in only or n[:-4] in only)})
    for name, make in wanted.items():
        if only and name not in only and name[:-4] not in only:
            continue
        path = os.path.join(out, name)
        if os.path.exists(path) and not force:
            print(f"{name}: cached ({os.path.getsize(path):,} bytes), skipped")
            continue
        t0 = time.time()
        grid = make()
        t1 = time.time()
        tmp = path + ".tmp"
        vdb.write(tmp, grids=[grid])
        G.patch_uuid(tmp)
        os.replace(tmp, path)
        t2 = time.time()
        lo, hi = grid.evalActiveVoxelBoundingBox() if grid.activeVoxelCount() else (None, None)
        print(f"{name}: {grid.activeVoxelCount():,} active voxels, {grid.leafCount():,} leaves, "
              f"bbox {lo}..{hi}, build {t1 - t0:.1f}s, write {t2 - t1:.1f}s, "
              f"{os.path.getsize(path):,} bytes")


if __name__ == "__main__":
    main(sys.argv[1:])
