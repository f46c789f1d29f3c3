"""Deterministic volume generators shared by make_fixtures.py and make_bench_inputs.py.

Run with /usr/bin/python3 (Debian's python3-openvdb + python3-numpy).
All generators are pure numpy and seeded, so the same parameters always give the same arrays.
Arrays are indexed [x, y, z] (pyopenvdb copyFromArray convention: array[i, j, k] -> voxel (i, j, k)).
"""
import hashlib
import math
import os

import numpy as np
import pyopenvdb as vdb


# ---------------------------------------------------------------------------
# fBm value noise (separable smooth interpolation of seeded random lattices)
# ---------------------------------------------------------------------------

def _axis_interp(lat, coords, axis):
    """Interpolate lattice `lat` along `axis` at float lattice coordinates `coords` (smoothstep)."""
    i0 = np.floor(coords).astype(np.int64)
    t = (coords - i0).astype(np.float32)
    t = t * t * (3.0 - 2.0 * t)
    a = np.take(lat, i0, axis=axis)
    b = np.take(lat, i0 + 1, axis=axis)
    shape = [1, 1, 1]
    shape[axis] = -1
    t = t.reshape(shape)
    return a + (b - a) * t


class FBm:
    """Value-noise fBm, output roughly in [0, 1].

    The noise is defined over a fixed integer domain [0, extent) per axis and can be evaluated on any
    axis-aligned sub-box (so large volumes can be built slab by slab with identical results).
    """

    def __init__(self, extent, base_period=32.0, octaves=5, lacunarity=2.0, gain=0.5, seed=1):
        self.octaves = []
        rng = np.random.default_rng(seed)
        period = float(base_period)
        amp = 1.0
        total = 0.0
        for _ in range(octaves):
            freq = 1.0 / period
            lshape = tuple(int(math.ceil(e * freq)) + 3 for e in extent)
            lat = rng.random(lshape, dtype=np.float32)
            # random per-octave offset so lattice points of different octaves do not line up
            off = rng.random(3) * 0.999
            self.octaves.append((freq, off, lat, amp))
            total += amp
            amp *= gain
            period /= lacunarity
            if period < 1.5:
                break
        self.norm = 1.0 / total

    def eval_box(self, x0, shape):
        """Evaluate on voxels x0 + [0, shape) (x0, shape: 3-tuples of ints). Returns float32 array."""
        out = np.zeros(shape, dtype=np.float32)
        for freq, off, lat, amp in self.octaves:
            v = lat
            for ax in range(3):
                c = (np.arange(x0[ax], x0[ax] + shape[ax], dtype=np.float64) + 0.5) * freq + off[ax]
                v = _axis_interp(v, c, ax)
            out += np.float32(amp) * v
        out *= np.float32(self.norm)
        return out


def smoothstep(e0, e1, x):
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


# ---------------------------------------------------------------------------
# Cumulus cloud
# ---------------------------------------------------------------------------

# Puffs in normalised box coordinates (u, v, w in [0,1], v = up/Y): centre, radii.
CUMULUS_PUFFS = [
    # cx,   cy,   cz,   rx,   ry,   rz
    (0.50, 0.36, 0.50, 0.47, 0.34, 0.44),   # main body
    (0.34, 0.44, 0.38, 0.26, 0.31, 0.26),
    (0.62, 0.52, 0.58, 0.29, 0.39, 0.29),   # tower
    (0.50, 0.68, 0.52, 0.20, 0.23, 0.21),   # top
    (0.30, 0.34, 0.68, 0.23, 0.21, 0.23),
    (0.70, 0.34, 0.30, 0.23, 0.20, 0.22),
]


def cumulus_box(dims, x0, shape, fbm, base=0.10, edge=0.10, noise_amp=0.55):
    """Density of a cumulus cloud filling a box of `dims` voxels, evaluated on sub-box x0+[0,shape).

    Shape field f = max over ellipsoid puffs of (1 - normalised radius), eroded by fBm, cut by a
    flat-ish base. Density = smoothstep(0, edge, f): 0 outside, 1 deep inside, soft edges.
    """
    nx, ny, nz = dims
    xs = (np.arange(x0[0], x0[0] + shape[0], dtype=np.float32) + 0.5) / nx
    ys = (np.arange(x0[1], x0[1] + shape[1], dtype=np.float32) + 0.5) / ny
    zs = (np.arange(x0[2], x0[2] + shape[2], dtype=np.float32) + 0.5) / nz
    X = xs[:, None, None]
    Y = ys[None, :, None]
    Z = zs[None, None, :]
    f = np.full(shape, -1.0, dtype=np.float32)
    for cx, cy, cz, rx, ry, rz in CUMULUS_PUFFS:
        r = np.sqrt(((X - cx) / rx) ** 2 + ((Y - cy) / ry) ** 2 + ((Z - cz) / rz) ** 2)
        np.maximum(f, 1.0 - r, out=f)
    n = fbm.eval_box(x0, shape)
    # erosion strongest at the edges, little in the core; billows on top, flatter base
    f = f - noise_amp * (1.0 - n) * (0.35 + 0.65 * np.clip(1.0 - f * 2.0, 0.0, 1.0))
    # flat-ish base: a thin soft cut above the bottom of the box, very slightly noisy
    f = np.minimum(f, (Y - base) * 4.0 + 0.03 * (n - 0.5))
    d = smoothstep(0.0, edge, f).astype(np.float32)
    d[d < 1e-4] = 0.0
    return d


def cumulus_grid(dims, seed, base_period, octaves=5, slab=64):
    fbm = FBm(dims, base_period=base_period, octaves=octaves, seed=seed)
    grid = fog_grid()
    for x in range(0, dims[0], slab):
        sx = min(slab, dims[0] - x)
        a = cumulus_box(dims, (x, 0, 0), (sx, dims[1], dims[2]), fbm)
        grid.copyFromArray(a, ijk=(x, 0, 0), tolerance=0.0)
    grid.prune(0.0)
    return grid


# ---------------------------------------------------------------------------
# Two intertwined rings (chain links)
# ---------------------------------------------------------------------------

def rings_box(center, R, r, x0, shape, edge=1.0):
    """Ring A in the XY plane around `center`; ring B in the XZ plane around center + (R,0,0).
    Uniform density 1 inside the tubes, linear soft edge `edge` voxels wide centred on the surface."""
    cx, cy, cz = center
    X = np.arange(x0[0], x0[0] + shape[0], dtype=np.float32)[:, None, None]
    Y = np.arange(x0[1], x0[1] + shape[1], dtype=np.float32)[None, :, None]
    Z = np.arange(x0[2], x0[2] + shape[2], dtype=np.float32)[None, None, :]
    qa = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2) - R
    da = np.sqrt(qa ** 2 + (Z - cz) ** 2) - r
    qb = np.sqrt((X - (cx + R)) ** 2 + (Z - cz) ** 2) - R
    db = np.sqrt(qb ** 2 + (Y - cy) ** 2) - r
    d = np.minimum(da, db)
    return np.clip(0.5 - d / edge, 0.0, 1.0).astype(np.float32)


def rings_grid(dims, R, r, slab=32):
    margin_x = (dims[0] - (3 * R + 2 * r)) / 2.0
    center = (math.floor(margin_x + R + r), dims[1] // 2, dims[2] // 2)
    grid = fog_grid()
    for x in range(0, dims[0], slab):
        sx = min(slab, dims[0] - x)
        a = rings_box(center, R, r, (x, 0, 0), (sx, dims[1], dims[2]))
        grid.copyFromArray(a, ijk=(x, 0, 0), tolerance=0.0)
    grid.prune(0.0)
    return grid


# ---------------------------------------------------------------------------
# Thin smoke helix, built sparsely block by block near the curve
# ---------------------------------------------------------------------------

def helix_grid(box=600, helix_radius=180.0, turns=4.0, tube=6.0, block=16, seed=7):
    c = box / 2.0
    z0, z1 = 40.0, box - 40.0        # helix axis along Y (up), from y=z0 to y=z1
    length = turns * math.sqrt((2 * math.pi * helix_radius) ** 2 + ((z1 - z0) / turns) ** 2)
    n = int(length / 0.4) + 1         # curve samples every ~0.4 voxel
    t = np.linspace(0.0, 1.0, n)
    ang = 2 * math.pi * turns * t
    P = np.stack([c + helix_radius * np.cos(ang), z0 + (z1 - z0) * t, c + helix_radius * np.sin(ang)], axis=1)
    rng = np.random.default_rng(seed)
    # slowly varying density along the curve (smoke-like puffiness), deterministic
    k = np.arange(1, 9)
    phase = rng.random(8) * 2 * math.pi
    amp = rng.random(8) / k
    mod = 0.65 + 0.35 * np.tanh((amp[None, :] * np.sin(2 * math.pi * k[None, :] * turns * 3 * t[:, None] + phase)).sum(1))
    reach = tube + 1.0
    # blocks touched by the tube
    blk = np.floor(P / block).astype(np.int64)
    pad = int(math.ceil(reach / block))
    cand = set()
    for b in np.unique(blk, axis=0):
        for dx in range(-pad, pad + 1):
            for dy in range(-pad, pad + 1):
                for dz in range(-pad, pad + 1):
                    cand.add((b[0] + dx, b[1] + dy, b[2] + dz))
    grid = fog_grid()
    half_diag = block * math.sqrt(3) / 2.0
    for b in sorted(cand):
        o = np.array(b) * block
        ctr = o + (block - 1) / 2.0
        dist = np.linalg.norm(P - ctr, axis=1)
        sel = dist < half_diag + reach
        if not sel.any():
            continue
        S = P[sel].astype(np.float32)
        M = mod[sel].astype(np.float32)
        g = np.stack(np.meshgrid(*[np.arange(o[i], o[i] + block, dtype=np.float32) for i in range(3)],
                                 indexing="ij"), axis=-1).reshape(-1, 3)
        d2 = ((g[:, None, :] - S[None, :, :]) ** 2).sum(-1)
        j = d2.argmin(1)
        d = np.sqrt(d2[np.arange(len(g)), j])
        x = np.clip(1.0 - d / tube, 0.0, 1.0)
        dens = (x * x * (3 - 2 * x)) * M[j]
        dens[dens < 1e-3] = 0.0
        if not dens.any():
            continue
        grid.copyFromArray(dens.reshape(block, block, block).astype(np.float32),
                           ijk=tuple(int(v) for v in o), tolerance=0.0)
    grid.prune(0.0)
    return grid


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def fog_grid(name="density"):
    g = vdb.FloatGrid(0.0)
    g.name = name
    g.gridClass = vdb.GridClass.FOG_VOLUME
    return g


def block_grid(lo, hi, value, name="density"):
    g = fog_grid(name)
    g.fill(lo, hi, value, active=True)
    return g


def fixed_uuid(filename):
    """Deterministic UUID-shaped ASCII string (8-4-4-4-12 lowercase hex) derived from the file name."""
    h = hashlib.sha256(os.path.basename(filename).encode()).hexdigest()[:32]
    return f"{h[0:8]}-{h[8:12]}-{h[12:16]}-{h[16:20]}-{h[20:32]}"


def patch_uuid(path):
    u = fixed_uuid(path).encode("ascii")
    assert len(u) == 36
    with open(path, "r+b") as f:
        head = f.read(57)
        assert head[:8] == b"\x20\x42\x44\x56\x00\x00\x00\x00", path
        ver = int.from_bytes(head[8:12], "little")
        assert ver >= 222, (path, ver)
        f.seek(21)
        f.write(u)
