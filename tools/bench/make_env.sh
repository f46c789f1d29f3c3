#!/usr/bin/env bash
# Writes a W×H latlong HDRI (uncompressed float OpenEXR, RGB) for the projection/relight benchmarks:
# a blue-grey sky gradient, dark ground and three soft coloured lobes, closed form at pixel centres
# (the latlong mapping of docs/model.md). Deterministic; needs numpy (/usr/bin/python3, python3-numpy).
# Usage: tools/bench/make_env.sh OUT.exr [WIDTH [HEIGHT]]     (default 2048×1024)
set -euo pipefail
OUT="$1"; W="${2:-2048}"; H="${3:-$(( W / 2 ))}"
/usr/bin/python3 - "$OUT" "$W" "$H" <<'PYEOF'
import os, struct, sys
import numpy as np
out, w, h = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
u = (np.arange(w) + 0.5) / w
v = (np.arange(h) + 0.5) / h
th, ph = np.pi * v[:, None], 2 * np.pi * u[None, :]
d = np.stack([np.sin(th) * np.sin(ph), np.cos(th) + 0 * ph, -np.sin(th) * np.cos(ph)], axis=-1)
y = d[..., 1:2]
rgb = np.where(y > 0, np.array([0.35, 0.45, 0.7]) * (0.4 + 0.6 * (1 - y)), np.array([0.08, 0.07, 0.06]))
for elev, azim, width, col in [(30, 60, 12, (8, 4, 1)), (10, 200, 18, (1, 2, 6)), (60, 300, 8, (1, 6, 1))]:
    t, p = np.radians(90 - elev), np.radians(azim)
    c = np.array([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)])
    ang = np.arccos(np.clip(d @ c, -1, 1))
    rgb = rgb + np.exp(-(ang / np.radians(width)) ** 2)[..., None] * np.array(col)
names = ["B", "G", "R"]
planes = {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]}
def attr(name, typ, data):
    return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(data)) + data
ch = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for n in names) + b"\0"
box = struct.pack("<iiii", 0, 0, w - 1, h - 1)
header = (b"\x76\x2f\x31\x01" + struct.pack("<i", 2) + attr("channels", "chlist", ch)
          + attr("compression", "compression", b"\0") + attr("dataWindow", "box2i", box)
          + attr("displayWindow", "box2i", box) + attr("lineOrder", "lineOrder", b"\0")
          + attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
          + attr("screenWindowCenter", "v2f", struct.pack("<ff", 0, 0))
          + attr("screenWindowWidth", "float", struct.pack("<f", 1.0)) + b"\0")
lines = [b"".join(planes[n][yy].astype("<f4").tobytes() for n in names) for yy in range(h)]
pos, offs = len(header) + 8 * h, []
for line in lines:
    offs.append(pos); pos += 8 + len(line)
tmp = out + ".tmp"
with open(tmp, "wb") as f:
    f.write(header + struct.pack("<%dQ" % h, *offs))
    for yy, line in enumerate(lines):
        f.write(struct.pack("<ii", yy, len(line)) + line)
os.replace(tmp, out)
PYEOF
