# Helpers for tools/bench.sh (sourced). Every measured run goes through `run_timed`, which wraps it in
# /usr/bin/time -v and keeps stdout, stderr, the --stats JSON line and the time report in $BENCH_OUT/log.
# shellcheck shell=bash

BENCH_IN="${BENCH_IN:-$PWD/target/bench-inputs}"
BENCH_OUT="${BENCH_OUT:-$PWD/target/bench-out}"
LOG="$BENCH_OUT/log"
mkdir -p "$LOG" "$BENCH_OUT/caches"

apt_install() {   # apt_install PACKAGE... (only as root; otherwise say what is missing)
    if [ "$(id -u)" = 0 ]; then
        DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "$@" >/dev/null 2>&1 \
            || { apt-get update >/dev/null 2>&1 && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends "$@" >/dev/null; }
    else
        echo "bench.sh: missing $*; install with apt-get install $*" >&2
        return 1
    fi
}

need_tools() {
    [ -x /usr/bin/time ] || apt_install time
    command -v jq >/dev/null || apt_install jq
}

# Builds the release binary (retrying while another developer's edit breaks the build) and copies it,
# so a rebuild during the benchmark cannot change the binary under measurement.
VS=""
build_vscatter() {
    [ -n "$VS" ] && return 0
    local tries=0
    until cargo build --release --quiet 2>"$LOG/build.err"; do
        tries=$((tries + 1))
        if [ $tries -ge 5 ]; then
            echo "bench.sh: cargo build --release failed 5 times:" >&2; tail -20 "$LOG/build.err" >&2; exit 1
        fi
        echo "bench.sh: build failed (concurrent edit?), retrying in 60 s" >&2
        sleep 60
    done
    # copy + rename: a bench run still using the previous copy keeps its file ("Text file busy" otherwise)
    cp target/release/vscatter "$BENCH_OUT/vscatter.tmp.$$"
    mv -f "$BENCH_OUT/vscatter.tmp.$$" "$BENCH_OUT/vscatter"
    VS="$BENCH_OUT/vscatter"
    echo "vscatter: $(git rev-parse --short HEAD)$(git diff --quiet HEAD -- src Cargo.toml Cargo.lock || echo '+dirty') built $(date -u +%FT%TZ); $(nproc) cores"
}

ensure_inputs() { tools/make_bench_inputs.sh "$BENCH_IN" >"$LOG/inputs.log" 2>&1 || { cat "$LOG/inputs.log" >&2; exit 1; }; }

load() { cut -d' ' -f1-3 /proc/loadavg; }

# logged_wall NAME : the wall time (s) of run_timed's run NAME, from its /usr/bin/time log.
logged_wall() {
    awk -F': ' '/Elapsed \(wall clock\)/{n=split($2,a,":"); s=0; for(i=1;i<=n;i++) s=s*60+a[i]; printf "%.2f", s}' "$LOG/$1.time"
}

# run_timed NAME CMD... : runs CMD under /usr/bin/time -v. Sets WALL (s), RSS_MB, CPU (% of one core the
# run got: 2 cores fully = 200%), CPU_S (user+sys seconds), RC, LOAD (at start),
# and NAME.json = the last JSON line of stdout (the --stats line), if any. Never aborts the bench.
run_timed() {
    local name="$1"; shift
    LOAD="$(load)"
    set +e
    /usr/bin/time -v -o "$LOG/$name.time" "$@" >"$LOG/$name.out" 2>"$LOG/$name.err"
    RC=$?
    set -e
    WALL=$(logged_wall "$name")
    RSS_MB=$(awk -F': ' '/Maximum resident set size/{printf "%.1f", $2/1024}' "$LOG/$name.time")
    CPU=$(awk -F': ' '/Percent of CPU/{print $2}' "$LOG/$name.time")
    CPU_S=$(awk -F': ' '/User time|System time/{s+=$2} END{printf "%.2f", s}' "$LOG/$name.time")
    grep '^{' "$LOG/$name.out" | tail -1 >"$LOG/$name.json" || true
    if [ "$RC" != 0 ]; then
        echo "FAILED ($name, exit $RC): $(grep -v '^\s*Command' "$LOG/$name.err" | grep -v '^$' | tail -1)" >&2
    fi
    return 0
}

# j NAME FIELD [FORMAT] : a field of NAME's --stats JSON ("-" when absent)
j() {
    local v
    v=$(jq -r --arg f "$2" '.[$f] // empty' "$LOG/$1.json" 2>/dev/null || true)
    if [ -z "$v" ]; then echo "-"; elif [ -n "${3:-}" ]; then printf "$3" "$v"; else echo "$v"; fi
}

# wall_of CMD... : wall seconds of one run (bash's microsecond clock), its output discarded; "-" and a
# FAILED line on stderr when the run fails, so a failure never passes for a time.
wall_of() {
    local t0=$EPOCHREALTIME rc=0
    "$@" >/dev/null 2>"$LOG/wall_of.err" || rc=$?
    if [ "$rc" != 0 ]; then
        echo "FAILED (exit $rc): $* : $(tail -1 "$LOG/wall_of.err")" >&2
        echo "-"
        return 0
    fi
    awk -v a="$t0" -v b="$EPOCHREALTIME" 'BEGIN{ printf "%.3f", b - a }'
}
# median VALUES... : the middle value (the mean of the two middle ones for an even count); "-" when
# any value is "-" (a failed run), never a median of the runs that happened to work.
median() {
    case " $* " in *" - "*) echo "-"; return 0 ;; esac
    printf "%s\n" "$@" | sort -g | awk '{ v[NR] = $1 } END{
        if (NR % 2) printf "%.3f", v[(NR + 1) / 2]; else printf "%.3f", (v[NR / 2] + v[NR / 2 + 1]) / 2 }'
}
mib() { awk -v b="$1" 'BEGIN{ if (b=="-") print "-"; else printf "%.1f", b/1048576 }'; }
# Three decimals: a verdict against a target such as 0.2 must not pass on rounding.
ratio() { awk -v a="$1" -v b="$2" 'BEGIN{ if (a=="-"||b=="-"||b==0) print "-"; else printf "%.3f", a/b }'; }
# verdict VALUE OP LIMIT : "ok" or "MISS (x1.23 of target)"
verdict() {
    awk -v v="$1" -v op="$2" -v t="$3" 'BEGIN{
        if (v=="-") { print "n/a"; exit }
        ok = (op=="<=") ? (v<=t) : (v<t)
        if (ok) print "ok"; else printf "MISS (%.2fx the target)\n", v/t }'
}

# info_field FILE FIELD : a field of the first grid of `vscatter info --json FILE`
info_field() { "$VS" info --json "$1" | jq -r ".grids[0].$2"; }

# bake_cache NAME VDB BAKE_ARGS... : bakes $BENCH_OUT/caches/NAME.vtc (measured as run "bake_NAME") and
# stamps it with the binary and arguments, so ensure_cache can reuse it (the bake section serves render).
bake_cache() {
    local name="$1" vdb="$2"; shift 2
    local vtc="$BENCH_OUT/caches/$name.vtc" stamp="$BENCH_OUT/caches/$name.args"
    rm -f "$stamp"
    run_timed "bake_$name" "$VS" bake "$vdb" -o "$vtc" "$@" --quiet --stats
    [ "$RC" = 0 ] && echo "$(sha1sum "$VS" | cut -c1-12) $vdb $*" >"$stamp"
    return 0
}

# ensure_cache NAME VDB BAKE_ARGS... : bake_cache unless a cache from this binary with these arguments exists.
ensure_cache() {
    local name="$1" vdb="$2"; shift 2
    local stamp="$BENCH_OUT/caches/$name.args"
    if [ -f "$BENCH_OUT/caches/$name.vtc" ] && [ -f "$stamp" ] \
        && [ "$(cat "$stamp")" = "$(sha1sum "$VS" | cut -c1-12) $vdb $*" ]; then
        return 0
    fi
    bake_cache "$name" "$vdb" "$@"
}
cache() { echo "$BENCH_OUT/caches/$1.vtc"; }

# camera_for VDB : sets CAM_POS and CAM_AT (world), a +Z view of the active bbox for a 45° horizontal,
# 16:9 frame; CAM_AT is the bbox centre as vdb_render computes it ((min+max)/2 in index space).
camera_for() {
    local js; js="$("$VS" info --json "$1")"
    read -r CAM_POS CAM_AT < <(jq -r '.grids[0] | [.bbox_min, .bbox_max, .scale, .translation] | @json' <<<"$js" \
        | python3 -c '
import json, math, sys
lo, hi, s, t = json.loads(sys.stdin.read())
c = [((lo[i] + hi[i]) / 2) * s[i] + t[i] for i in range(3)]
h = [(hi[i] - lo[i] + 1) / 2 * abs(s[i]) for i in range(3)]
th = math.tan(math.radians(22.5)); tv = th * 9 / 16
d = h[2] + 1.1 * max(h[0] / th, h[1] / tv)
f = lambda v: ",".join("%.3f" % x for x in v)
print(f([c[0], c[1], c[2] + d]), f(c))')
}
