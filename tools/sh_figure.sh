#!/usr/bin/env bash
# Reproduces thesis fig. 6.4: the sky-with-sun fixture projected onto 5, 10 and 15 SH bands and
# reconstructed, without and with the Hamming window of eq. 6.1. Writes into docs/:
#   sh_original.png, sh_{5,10,15}_{none,hamming}.png  (tonemapped latlongs, 256×128)
#   sh_figure.png                                     (contact sheet, labelled)
#   sh_figure.txt                                     (relative L2 errors per panel)
# Needs ImageMagick's `montage` for the contact sheet (installed with apt-get when missing and root).
set -euo pipefail
cd "$(dirname "$0")/.."
ENV=fixtures/env/sky_sun.exr
OUT=docs
mkdir -p "$OUT"

if ! command -v montage >/dev/null; then
    if [ "$(id -u)" = 0 ]; then
        DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends imagemagick fonts-dejavu-core >/dev/null
    else
        echo "sh_figure.sh: needs ImageMagick's montage (apt-get install imagemagick)" >&2
        exit 1
    fi
fi

cargo build --release --quiet
VS=target/release/vscatter

: > "$OUT/sh_figure.txt"
tiles=("$OUT/sh_original.png" "null:")
labels=("original ($ENV)" "")
for bands in 5 10 15; do
    for window in none hamming; do
        png="$OUT/sh_${bands}_${window}.png"
        args=(env "$ENV" -o "$png" --bands "$bands" --window "$window")
        [ "$bands" = 5 ] && [ "$window" = none ] && args+=(--original "$OUT/sh_original.png")
        err=$("$VS" "${args[@]}" | sed -n 's/^relative L2 error.*: //p')
        echo "bands=$bands window=$window relative_L2_error=$err" | tee -a "$OUT/sh_figure.txt"
        tiles+=("$png")
        labels+=("$bands bands, window $window")
    done
done

# Contact sheet: original on top, then one row per band count, unwindowed left, windowed right.
margs=()
for i in "${!tiles[@]}"; do
    margs+=(-label "${labels[$i]}" "${tiles[$i]}")
done
montage "${margs[@]}" -tile 2x4 -geometry +4+4 -font DejaVu-Sans -pointsize 12 -background white \
    -define png:compression-level=9 "$OUT/sh_figure.png"
ls -l "$OUT"/sh_*.png
