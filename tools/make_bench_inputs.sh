#!/usr/bin/env bash
# Generate the benchmark volumes into OUTDIR (default target/bench-inputs). Existing files are kept.
# Usage: tools/make_bench_inputs.sh [OUTDIR] [--only NAME,...] [--force]
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
OUT="${1:-$ROOT/target/bench-inputs}"
[ $# -gt 0 ] && shift
source "$ROOT/tools/need_openvdb.sh"
need_openvdb
exec /usr/bin/python3 "$ROOT/tools/make_bench_inputs.py" "$OUT" "$@"
