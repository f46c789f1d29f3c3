#!/usr/bin/env bash
# Fuzzes the VDB reader (tools/fuzz/fuzz_targets/vdb_reader.rs) with libFuzzer, seeded with the
# small fixtures of every kind. Needs a nightly toolchain and cargo-fuzz (`cargo install cargo-fuzz`).
#   tools/fuzz/run.sh [SECONDS]     default 3600; findings land in tools/fuzz/artifacts/
set -euo pipefail
cd "$(dirname "$0")/../.."
SECONDS_TO_RUN="${1:-3600}"
CORPUS=target/fuzz-corpus
mkdir -p "$CORPUS"
for f in small_cloud small_cloud_half small_cloud_zip smoke_double_openvdb7 multi vec3_only \
         block_tiles huge_root_tile huge_tiles_2048 empty; do
    cp -n "fixtures/$f.vdb" "$CORPUS/" 2>/dev/null || true
done
# 2 GB of RSS and 1 GB in one allocation: a forged count that asks for more is a finding.
exec cargo +nightly fuzz run --fuzz-dir tools/fuzz vdb_reader "$CORPUS" -- \
    -max_total_time="$SECONDS_TO_RUN" -rss_limit_mb=2048 -malloc_limit_mb=1024 -max_len=400000 \
    -print_final_stats=1
