#!/usr/bin/env bash
# Dirty images with the w-term against WSClean by field size: VLA D simulated at low
# frequency (r2d2 simulate, which predicts with the w-term where it matters), written as an
# MS by tests/make_ms.py (python-casacore), imaged by `r2d2 dirty` (w-term auto, and off) and
# by WSClean twice: converged (w-stacking with 200 layers, padding 2, kernel 15) and with its
# defaults. Prints a markdown row per field: 2-norm relative / max |diff| over the peak.
#   bash benches/wterm_vs_wsclean.sh [R2D2 binary]      (needs wsclean, python-casacore, astropy)
set -euo pipefail
R2D2=$(realpath "${1:-target/release/r2d2}")
HERE=$(cd "$(dirname "$0")/.." && pwd)
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
echo "| image | field | largest w-phase (rad) | w-planes | r2d2 (w-term) vs WSClean | r2d2 --w-term off vs WSClean | WSClean default vs converged |"
echo "|---|---|---|---|---|---|---|"
for cfg in "64 74" "128 74" "256 74" "256 38"; do
    set -- $cfg
    SIZE=$1 FREQ=$2
    D="$WORK/$SIZE-$FREQ"
    mkdir -p "$D" && cd "$D"
    "$R2D2" -q simulate --configs d --freq-mhz "$FREQ" --hours 4 --integration-s 600 --size "$SIZE" --dec 40 --dr 1000 --seed 6 --out obs.parquet
    python3 "$HERE/tests/make_ms.py" obs.parquet obs.ms > /dev/null
    "$R2D2" dirty obs.ms --size "$SIZE" --weighting natural --name r2 > r2.log 2>&1
    "$R2D2" -q dirty obs.ms --size "$SIZE" --weighting natural --w-term off --name flat 2> /dev/null
    S=$(python3 -c "from astropy.io import fits; print(abs(fits.getheader('r2-dirty.fits')['CDELT1']) * 3600)")
    wsclean -quiet -weight natural -niter 0 -size "$SIZE" "$SIZE" -scale "${S}asec" -nwlayers 200 -padding 2 -oversampling 4095 -kernel-size 15 -j 2 -name ws obs.ms > ws.log 2>&1
    wsclean -quiet -weight natural -niter 0 -size "$SIZE" "$SIZE" -scale "${S}asec" -j 2 -name wsd obs.ms > wsd.log 2>&1
    python3 - "$SIZE" "$FREQ" <<'PY'
import re, sys
import numpy as np
from astropy.io import fits
size, freq = sys.argv[1:3]
read = lambda name: fits.getdata(f"{name}-dirty.fits").squeeze()
r2, flat, ws, wsd = read("r2"), read("flat"), read("ws"), read("wsd")
field = abs(fits.getheader("r2-dirty.fits")["CDELT1"]) * r2.shape[0]
fmt = lambda a, b: f"{np.linalg.norm(a - b) / np.linalg.norm(b):.1e} / {np.abs(a - b).max() / np.abs(b).max():.1e}"
m = re.search(r"(\d+) w-planes; up to ([0-9.]+) rad", open("r2.log").read())
planes, phase = (m.group(1), m.group(2)) if m else ("-", "-")
print(f"| {size} px, {freq} MHz | {field:.1f} deg | {phase} | {planes} | {fmt(r2, ws)} | {fmt(flat, ws)} | {fmt(wsd, ws)} |")
PY
done
