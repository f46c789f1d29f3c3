#!/usr/bin/env bash
# Regenerate vscatter's test fixtures in fixtures/ (deterministic: a rerun gives byte-identical files).
# Uses Debian's OpenVDB 10 tools (vdb_tool, vdb_print) and python3-openvdb via /usr/bin/python3.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${1:-$ROOT/fixtures}"
PY=/usr/bin/python3

source "$ROOT/tools/need_openvdb.sh"
need_openvdb

mkdir -p "$OUT"
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT

# Quiet vdb_tool unless it fails.
vt() { vdb_tool "$@" >"$TMP/vdb_tool.log" 2>&1 || { cat "$TMP/vdb_tool.log" >&2; exit 1; }; }

# 1. Level-set sphere (radius 20 voxels, voxel size 1, half-width 3) and its fog volume "density".
vt -sphere voxel=1 radius=20 width=3 name=sphere_ls -write keep=1 "$OUT/sphere_ls.vdb" \
   -ls2fog name=density -write "$OUT/sphere_fog.vdb"

# 2. pyopenvdb fixtures: cloud, torus, block_tiles, small_cloud, multi, empty, vec3_only.
"$PY" "$ROOT/tools/make_fixtures.py" gen "$OUT"

# 3. Codec variants of small_cloud written by vdb_tool.
#    OpenVDB clears ZIP for fog volumes and level sets, so the ZIP variant is written from a copy
#    whose grid class is "unknown".
"$PY" "$ROOT/tools/make_fixtures.py" reclass "$OUT/small_cloud.vdb" "$TMP/small_cloud_unknown.vdb"
vt -read "$TMP/small_cloud_unknown.vdb" -write codec=zip "$OUT/small_cloud_zip.vdb"
vt -read "$OUT/small_cloud.vdb" -write bits=16 "$OUT/small_cloud_half.vdb"
vt -read "$OUT/small_cloud.vdb" -write codec=none "$OUT/small_cloud_raw.vdb"

# 4. Fixed header UUIDs, cross-check with vdb_print -l, expected.json.
"$PY" "$ROOT/tools/make_fixtures.py" finalize "$OUT"
"$PY" "$ROOT/tools/make_fixtures.py" inspect "$OUT"/*.vdb
