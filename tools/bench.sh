#!/usr/bin/env bash
# Benchmarks, in named sections. Run all:   tools/bench.sh
# or some:                                  tools/bench.sh sh_project ...
# To add a section: write a function `section_NAME` below and append NAME to SECTIONS.
# Each section prints lines "NAME ...: figures"; release builds, so the first run compiles.
set -euo pipefail
cd "$(dirname "$0")/.."

# SH projection and reconstruction of a 4096×2048 latlong map at 10 and 20 bands
# (benches/sh_project.rs; the map is the built-in sky generated in memory, nothing on disk).
section_sh_project() {
    cargo bench --quiet --bench sh_project
}

SECTIONS=(sh_project)

run=("$@")
[ ${#run[@]} -eq 0 ] && run=("${SECTIONS[@]}")
for s in "${run[@]}"; do
    if ! declare -F "section_$s" >/dev/null; then
        echo "bench.sh: unknown section '$s' (have: ${SECTIONS[*]})" >&2
        exit 2
    fi
    echo "== $s"
    "section_$s"
done
