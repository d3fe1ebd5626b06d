#!/usr/bin/env bash
# Rebuild the shipped series models/vla-r2d2-128 from nothing, seeded end to end:
#   training/reproduce.sh [DATA_DIR]        (default training/data, git-ignored)
# Steps whose output exists are skipped, so rerunning the script resumes it; training itself
# resumes from its per-epoch checkpoint and adds networks to the series (--resume).
# Environment: R2D2 (the engine binary, default target/release/r2d2), SERIES (default
# models/vla-r2d2-128), TRAIN_ARGS (extra train.py options, e.g. "--max-networks 20").
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-training/data}
R2D2=${R2D2:-target/release/r2d2}
SERIES=${SERIES:-models/vla-r2d2-128}
SIM="--size 128 --integration-s 300 --epsilon 1e-5"
mkdir -p "$DATA"
[ -x "$R2D2" ] || cargo build --release
[ -d "$DATA/truths-train" ] || python3 training/prepare_truths.py --count 640 --size 128 --seed 1 --source-dr 50 --out "$DATA/truths-train"
[ -d "$DATA/train" ] || "$R2D2" trainset --truths "$DATA/truths-train" --source-dr 50 --seed 1 $SIM --out "$DATA/train"
[ -d "$DATA/val" ] || "$R2D2" trainset --procedural 48 --seed 500000 $SIM --out "$DATA/val"
[ -d "$DATA/test" ] || "$R2D2" trainset --procedural 32 --seed 900000 $SIM --parquet --out "$DATA/test"
RESUME=""
[ -f "$SERIES/manifest.yaml" ] && RESUME="--resume"
python3 training/train.py --train "$DATA/train" --val "$DATA/val" --series "$SERIES" --work "$DATA/work" \
    --epochs-first 16 --epochs 6 --batch 8 --bf16 --seed 1 --threads 2 --max-networks 12 $RESUME ${TRAIN_ARGS:-}
python3 training/evaluate.py --series "$SERIES" --test "$DATA/test" --r2d2 "$R2D2" --out "$DATA/eval" --update-manifest
