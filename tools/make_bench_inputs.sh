#!/usr/bin/env bash
# Generate the benchmark volumes into OUTDIR (default target/bench-inputs). Existing files are kept.
# Usage: tools/make_bench_inputs.sh [OUTDIR] [--only NAME,...] [--force]
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${1:-$ROOT/target/bench-inputs}"
[ $# -gt 0 ] && shift
if ! /usr/bin/python3 -c 'import pyopenvdb, numpy' >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO=sudo
    $SUDO apt-get update
    $SUDO apt-get install -y libopenvdb-tools python3-openvdb python3-numpy
fi
exec /usr/bin/python3 "$ROOT/tools/make_bench_inputs.py" "$OUT" "$@"
