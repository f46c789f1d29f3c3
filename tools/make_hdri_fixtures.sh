#!/usr/bin/env bash
# Regenerates the small latlong HDRI fixtures in fixtures/env/ (see fixtures/env/README.md).
#
# Deterministic: closed-form radiance at pixel centres (4×4 supersampled), written by the tiny
# uncompressed OpenEXR / flat RGBE writers below, so the bytes only depend on this script.
# Needs numpy: Debian's /usr/bin/python3 has it (apt-get install python3-numpy).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=/usr/bin/python3
"$PY" -c 'import numpy' 2>/dev/null || { echo "need numpy for $PY (apt-get install python3-numpy)" >&2; exit 1; }
mkdir -p fixtures/env
"$PY" - fixtures/env <<'PYEOF'
import struct, sys
import numpy as np

out = sys.argv[1]

def directions(w, h, ss=4):
    """Unit directions of ss×ss sub-samples per pixel, shape (h, w, ss*ss, 3), the latlong
    mapping of docs/model.md:
    theta = pi*v from +Y, phi = 2*pi*u, omega = (sin t sin p, cos t, -sin t cos p)."""
    o = (np.arange(ss) + 0.5) / ss
    u = (np.arange(w)[:, None] + o[None, :]) / w          # (w, ss)
    v = (np.arange(h)[:, None] + o[None, :]) / h          # (h, ss)
    th = np.pi * v[:, None, :, None]                      # (h,1,ss,1)
    ph = 2 * np.pi * u[None, :, None, :]                  # (1,w,1,ss)
    x = np.sin(th) * np.sin(ph)
    y = np.cos(th) * np.ones_like(ph)
    z = -np.sin(th) * np.cos(ph)
    d = np.stack(np.broadcast_arrays(x, y, z), axis=-1)   # (h,w,ss,ss,3)
    return d.reshape(h, w, ss * ss, 3)

def dir_of(elev_deg, azim_deg):
    t, p = np.radians(90 - elev_deg), np.radians(azim_deg)
    return np.array([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)])

def smoothstep(a, b, x):
    t = np.clip((x - a) / (b - a), 0, 1)
    return t * t * (3 - 2 * t)

def write_exr(path, rgb, half=False, alpha=False):
    """Single-part scanline OpenEXR, no compression, one scanline per chunk."""
    h, w, _ = rgb.shape
    names = ["A", "B", "G", "R"] if alpha else ["B", "G", "R"]      # channel list sorted by name
    planes = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2], "A": np.ones((h, w))}
    ptype, dt = (1, "<f2") if half else (2, "<f4")
    def attr(name, typ, data):
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data
    ch = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", ptype, 0, 1, 1) for n in names) + b"\0"
    box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
    header = (b"\x76\x2f\x31\x01" + struct.pack("<i", 2)
              + attr("channels", "chlist", ch)
              + attr("compression", "compression", b"\0")
              + attr("dataWindow", "box2i", box)
              + attr("displayWindow", "box2i", box)
              + attr("lineOrder", "lineOrder", b"\0")
              + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
              + attr("screenWindowCenter", "v2f", struct.pack("<ff", 0, 0))
              + attr("screenWindowWidth", "float", struct.pack("<f", 1.0))
              + b"\0")
    lines = [b"".join(planes[n][y].astype(dt).tobytes() for n in names) for y in range(h)]
    pos = len(header) + 8 * h
    offsets = []
    for line in lines:
        offsets.append(pos)
        pos += 8 + len(line)
    with open(path, "wb") as f:
        f.write(header + struct.pack("<%dQ" % h, *offsets))
        for y, line in enumerate(lines):
            f.write(struct.pack("<ii", y, len(line)) + line)

def write_hdr(path, rgb):
    """Radiance RGBE, flat (uncompressed) scanlines, "-Y H +X W" orientation."""
    h, w, _ = rgb.shape
    m = rgb.max(axis=-1)
    e = np.where(m > 1e-32, np.floor(np.log2(np.maximum(m, 1e-32))) + 1, -128)
    scale = np.where(m > 1e-32, 256.0 / np.exp2(e), 0)
    mant = np.clip(np.floor(rgb * scale[..., None]), 0, 255).astype(np.uint8)
    ex = np.where(m > 1e-32, e + 128, 0).astype(np.uint8)
    data = np.concatenate([mant, ex[..., None]], axis=-1)
    with open(path, "wb") as f:
        f.write(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y %d +X %d\n" % (h, w))
        f.write(data.tobytes())

def render(w, h, fn):
    return fn(directions(w, h)).mean(axis=2)

# 1. constant: uniform white, the white-furnace environment.
write_exr(f"{out}/constant.exr", np.ones((64, 128, 3)))

# 2. sky_sun: blue gradient, dark ground, a small very bright warm sun (35° up, azimuth 180°:
#    centred in the image so figures show it). Its energy (≈ 7.7 per channel over 3.8e-3 sr) is
#    ≈ 3.5× the dome's irradiance on a horizontal surface: a clear-day balance, and still ≈ 2000×
#    the sky's radiance, the "single bright area" of thesis 6.5.2.
def sky(d):
    y = d[..., 1:2]
    t = (1 - np.maximum(y, 0)) ** 3
    skyc = np.array([0.25, 0.45, 1.0]) * (1 - t) + np.array([0.85, 0.92, 1.05]) * t
    s = smoothstep(-0.03, 0.03, y)
    c = np.array([0.16, 0.14, 0.12]) * (1 - s) + skyc * s
    sun = dir_of(35, 180)
    ang = np.arccos(np.clip(d @ sun, -1, 1))[..., None]
    return c + (ang < np.radians(2.0)) * np.array([2000.0, 1750.0, 1350.0])
write_exr(f"{out}/sky_sun.exr", render(256, 128, sky), half=True)

# 3. split: warm white upper hemisphere, dark brown lower one, boundary exactly at the horizon.
def split(d):
    up = d[..., 1:2] > 0
    return np.where(up, np.array([1.0, 0.95, 0.9]), np.array([0.2, 0.1, 0.05]))
write_exr(f"{out}/split.exr", render(128, 64, split))

# 4. studio: three soft coloured area lights on near-black (RGBA, float; also as .hdr).
def studio(d):
    c = np.full(d.shape[:-1] + (3,), 0.02)
    for elev, azim, width_deg, colour in [(30, 60, 12, [8.0, 3.0, 1.0]),
                                          (10, 200, 18, [1.0, 2.0, 6.0]),
                                          (60, 300, 8, [2.0, 9.0, 3.0])]:
        cosang = d @ dir_of(elev, azim)
        lobe = np.exp((cosang - 1) / (1 - np.cos(np.radians(width_deg))))
        c = c + lobe[..., None] * np.array(colour)
    return c
st = render(128, 64, studio)
write_exr(f"{out}/studio.exr", st, alpha=True)
write_hdr(f"{out}/studio.hdr", st)
PYEOF
ls -l fixtures/env
