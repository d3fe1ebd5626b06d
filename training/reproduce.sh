#!/usr/bin/env bash
# Rebuild a shipped series from nothing, seeded end to end:
#   training/reproduce.sh [vla-r2d2-512|meerkat-r2d2-512|vla-r2d2-512-broad|vla-r2d2-128] [DATA_DIR]
#   (default vla-r2d2-512, training/data)
# Steps whose output exists are skipped, so rerunning the script resumes it; training itself
# resumes from its per-epoch checkpoint and adds networks to the series (--resume).
# Environment: R2D2 (the engine binary, default target/release/r2d2), SERIES (default
# models/<recipe>), TRAIN_ARGS (extra train.py options for every stage of the recipe, e.g.
# "--device cpu"; a stage's network count: STAGE2_NETWORKS .. STAGE9_NETWORKS, or edit the recipe's ARGS),
# NICE (default 19: training yields the CPU to interactive work), WORK (per-epoch checkpoints,
# default <data>/work: give a retrain into another SERIES its own), THREADS (CPU threads of
# training, default 2), EVAL=0 (skip the held-out evaluation, e.g. on a machine lent for training).
set -euo pipefail
cd "$(dirname "$0")/.."
RECIPE=${1:-vla-r2d2-512}
DATA=${2:-training/data}
R2D2=${R2D2:-target/release/r2d2}
SERIES=${SERIES:-models/$RECIPE}
RUN="nice -n ${NICE:-19}"
[ -x "$R2D2" ] || cargo build --release
# make_once OUT COMMAND...: run COMMAND --out OUT at low priority unless OUT exists (resuming).
make_once() { local out=$1; shift; [ -d "$out" ] || $RUN "$@" --out "$out"; }
case "$RECIPE" in
vla-r2d2-128)
    D="$DATA/128"
    SIM="--size 128 --integration-s 300 --epsilon 1e-5"
    mkdir -p "$D"
    make_once "$D/truths-train" python3 training/prepare_truths.py --count 640 --size 128 --seed 1 --source-dr 50
    make_once "$D/train" "$R2D2" trainset --truths "$D/truths-train" --source-dr 50 --seed 1 $SIM
    make_once "$D/val" "$R2D2" trainset --procedural 48 --seed 500000 $SIM
    make_once "$D/test" "$R2D2" trainset --procedural 32 --seed 900000 $SIM --parquet
    TRAIN=("$D/train")
    VAL=("$D/val")
    ARGS="--epochs-first 16 --epochs 6 --batch 8 --bf16 --max-networks 12"
    ;;
vla-r2d2-512|meerkat-r2d2-512)
    # Training truths: 120 of the project's procedural radio skies (seeds 100000..) and 80
    # reworked scikit-image images; validation 500000.., test 900000..: disjoint seeds.
    # One recipe for every telescope: the observations are drawn from the telescope's
    # training preset (data/telescopes/telescopes.yaml); the VLA's integration time is 300 s.
    TELESCOPE=${RECIPE%-r2d2-512}
    if [ "$TELESCOPE" = vla ]; then
        D="$DATA/512"
        SIM="--size 512 --integration-s 300 --epsilon 1e-5"
    else
        D="$DATA/512-$TELESCOPE"
        SIM="--size 512 --telescope $TELESCOPE --epsilon 1e-5"
    fi
    mkdir -p "$D"
    make_once "$D/truths-train" python3 training/prepare_truths.py --count 80 --size 512 --seed 2 --source-dr 50
    make_once "$D/train-images" "$R2D2" trainset --truths "$D/truths-train" --source-dr 50 --seed 1000 $SIM
    make_once "$D/train-radio" "$R2D2" trainset --procedural 120 --seed 100000 $SIM
    make_once "$D/val" "$R2D2" trainset --procedural 16 --seed 500000 $SIM
    make_once "$D/test" "$R2D2" trainset --procedural 12 --seed 900000 $SIM --parquet
    TRAIN=("$D/train-radio" "$D/train-images")
    VAL=("$D/val")
    # Every stage: bias-free U-Nets on 4 crops of 128 a sample and epoch, batches of 8.
    CROPS="--norm none --crop 128 --crops-per-sample 4 --batch 8"
    ARGS="$CROPS --epochs-first 10 --epochs 4 --max-networks 15"
    if [ "$TELESCOPE" = vla ]; then
        # Stage 2 (networks 16..): faint extended emission. Skies of extended emission (seeds
        # 200000.., validation 510000.., test 910000..) beside the classic ones, at the series'
        # own setting; validated on both kinds (training/README.md, "Stage 2 of vla-r2d2-512").
        # The extended skies are smoothed to a resolution drawn in 1.5..3 pixels (as a real
        # radio image is made at a resolution): trained on texture finer than the data measure,
        # the networks learnt to add texture and lost SNR on resolved skies.
        RESOLVED="--truth-fwhm-px 1.5..3"
        make_once "$D/train-extended-resolved" "$R2D2" trainset --procedural 120 --sky extended --seed 200000 $RESOLVED $SIM
        make_once "$D/val-extended-resolved" "$R2D2" trainset --procedural 8 --sky extended --seed 510000 $RESOLVED $SIM
        if [ "${EVAL:-1}" != 0 ]; then
            # Held out: the extended skies as generated and smoothed to 2 pixels.
            make_once "$D/test-extended" "$R2D2" trainset --procedural 12 --sky extended --seed 910000 $SIM --parquet
            make_once "$D/test-extended-fwhm2" "$R2D2" trainset --procedural 12 --sky extended --seed 910000 --truth-fwhm-px 2 $SIM --parquet
        fi
        STAGE2_TRAIN=("$D/train-radio" "$D/train-extended-resolved")
        STAGE2_VAL=("$D/val" "$D/val-extended-resolved")
        # The stopping rule ended it at network 18 (a 19th did not improve validation): capped
        # there, so that a recipe resumed during stage 3 does not add 4-epoch networks.
        STAGE2="$CROPS --epochs 4 --max-networks ${STAGE2_NETWORKS:-18}"
        # Stage 3 (networks 19..): the same data, 8 epochs a network. Once the 4-epoch stage
        # stopped improving (network 19 rejected), longer training of each network still did.
        STAGE3="$CROPS --epochs 8 --max-networks ${STAGE3_NETWORKS:-25}"
        # Stage 4 (network 26): the same, the loss adding 0.1 x the L1 of the rlog images (the
        # faint emission's share); a 27th was refused by the stopping rule.
        STAGE4="$CROPS --epochs 8 --max-networks ${STAGE4_NETWORKS:-26} --loss-log-weight 0.1"
        # Stage 5 (network 27): field-filling skies (one object spanning the field inside a
        # faint cocoon, lumpy with turbulence; seeds 220000.., validation 520000.., test
        # 930000..), the plateau at 1e-4..1e-3 of the peak that real radio galaxies have over
        # a large part of the field, first and then stage 2's extended skies, 200 samples in
        # all (the replay of the series over each costs a network's inference and residual);
        # validated on stage 2's sets and the field-filling ones; stage 4's loss. A 28th
        # network was refused by the stopping rule.
        # field_filling_sets NAME SEED TEST_SEED TEST_FWHM SMOOTH...: 120 training skies
        # (seeds SEED.., train-field-filling-NAME) and 8 validation skies (SEED + 300000..)
        # smoothed as SMOOTH says, and 12 held-out ones (TEST_SEED..) smoothed to TEST_FWHM pixels.
        field_filling_sets() {
            local name=$1 seed=$2 test_seed=$3 test_fwhm=$4; shift 4
            make_once "$D/train-field-filling-$name" "$R2D2" trainset --procedural 120 --sky field-filling --seed "$seed" "$@" $SIM
            make_once "$D/val-field-filling-$name" "$R2D2" trainset --procedural 8 --sky field-filling --seed $((seed + 300000)) "$@" $SIM
            if [ "${EVAL:-1}" != 0 ]; then
                make_once "$D/test-field-filling-fwhm$test_fwhm" "$R2D2" trainset --procedural 12 --sky field-filling --seed "$test_seed" --truth-fwhm-px "$test_fwhm" $SIM --parquet
            fi
        }
        field_filling_sets resolved 220000 930000 2 $RESOLVED
        STAGE5_TRAIN=("$D/train-field-filling-resolved" "$D/train-extended-resolved")
        STAGE5_VAL=("${STAGE2_VAL[@]}" "$D/val-field-filling-resolved")
        STAGE5="$CROPS --epochs 8 --limit-train 200 --max-networks ${STAGE5_NETWORKS:-27} --loss-log-weight 0.1"
        # Stage 6 (networks 28..): sharper skies. Field-filling skies smoothed to only 1.2..1.8
        # pixels (seeds 240000.., validation 540000.., test 940000.. at 1.5 px) hold, as real
        # radio images do, a share of their energy beyond the longest baseline; 120 of them
        # and the first 80 of stage 5's field-filling skies, the linear loss, validated on
        # stage 5's sets and the sharp ones (training/README.md, "Stage 6").
        field_filling_sets sharp 240000 940000 1.5 --truth-fwhm-px 1.2..1.8
        STAGE6_TRAIN=("$D/train-field-filling-sharp" "$D/train-field-filling-resolved")
        STAGE6_VAL=("${STAGE5_VAL[@]}" "$D/val-field-filling-sharp")
        STAGE6="$CROPS --epochs 8 --limit-train 200 --max-networks ${STAGE6_NETWORKS:-37}"
        # Stage 7 (networks 38-39): twice the data. A 38th network trained on stage 6's 200
        # skies was refused; on 400 (120 more sharp field-filling skies, seeds 280000.., and
        # 40 of stage 2's extended ones beside stage 6's sets) networks 38 and 39 raised
        # validation and a 40th was refused (training/README.md, "Stage 7").
        # more_sharp_skies NAME SEED: 120 more training skies like stage 6's sharp ones (seeds
        # SEED..), train-field-filling-sharp-NAME.
        more_sharp_skies() {
            make_once "$D/train-field-filling-sharp-$1" "$R2D2" trainset --procedural 120 --sky field-filling --seed "$2" --truth-fwhm-px 1.2..1.8 $SIM
        }
        more_sharp_skies b 280000
        STAGE7_TRAIN=("$D/train-field-filling-sharp" "$D/train-field-filling-sharp-b" "$D/train-field-filling-resolved" "$D/train-extended-resolved")
        STAGE7_VAL=("${STAGE6_VAL[@]}")
        STAGE7="$CROPS --epochs 8 --limit-train 400 --max-networks ${STAGE7_NETWORKS:-39}"
        # Stage 8 (networks 40..): 120 more sharp field-filling skies (seeds 300000..), 520 in
        # all, the recipe otherwise stage 7's (training/README.md, "Stage 8").
        more_sharp_skies c 300000
        STAGE8_TRAIN=("$D/train-field-filling-sharp" "$D/train-field-filling-sharp-b" "$D/train-field-filling-sharp-c" "$D/train-field-filling-resolved" "$D/train-extended-resolved")
        STAGE8_VAL=("${STAGE6_VAL[@]}")
        STAGE8="$CROPS --epochs 8 --limit-train 520 --max-networks ${STAGE8_NETWORKS:-41}"
        # Stage 9 (networks 42..): 120 more (seeds 320000..), 640 in all (training/README.md,
        # "Stage 9").
        more_sharp_skies d 320000
        STAGE9_TRAIN=("$D/train-field-filling-sharp" "$D/train-field-filling-sharp-b" "$D/train-field-filling-sharp-c" "$D/train-field-filling-sharp-d" "$D/train-field-filling-resolved" "$D/train-extended-resolved")
        STAGE9_VAL=("${STAGE6_VAL[@]}")
        STAGE9="$CROPS --epochs 8 --limit-train 640 --max-networks ${STAGE9_NETWORKS:-43}"
    fi
    ;;
vla-r2d2-512-broad)
    # The reference v2's range of settings in one series: SR 1.5..2.5, Briggs -1..1 and
    # integration times drawn per sample (tracks and DR as in vla-r2d2-512), and skies with
    # extended emission (textured lobes, spiral disks, halos and relics) beside the classic
    # procedural ones and the reworked images. Seeds: training 1000.. (images), 100000..
    # (classic), 200000.. (extended); validation 500000.. (classic) and 510000.. (extended);
    # test 900000.. and
    # 910000..: disjoint from each other.
    D="$DATA/512-broad"
    SIM="--size 512 --epsilon 1e-5 --superresolution 1.5..2.5 --robust=-1..1 --integration-s 200..450"
    mkdir -p "$D"
    make_once "$D/truths-train" python3 training/prepare_truths.py --count 80 --size 512 --seed 2 --source-dr 50
    make_once "$D/train-images" "$R2D2" trainset --truths "$D/truths-train" --source-dr 50 --seed 1000 $SIM
    make_once "$D/train-radio" "$R2D2" trainset --procedural 80 --seed 100000 $SIM
    make_once "$D/train-extended" "$R2D2" trainset --procedural 120 --sky extended --seed 200000 $SIM
    # 120 more extended skies (seeds 200120..: the samples a 240-sky set from 200000 would hold).
    make_once "$D/train-extended-more" "$R2D2" trainset --procedural 120 --sky extended --seed 200120 $SIM
    make_once "$D/val-classic" "$R2D2" trainset --procedural 8 --seed 500000 $SIM
    make_once "$D/val-extended" "$R2D2" trainset --procedural 8 --sky extended --seed 510000 $SIM
    if [ "${EVAL:-1}" != 0 ]; then
        make_once "$D/test" "$R2D2" trainset --procedural 12 --seed 900000 $SIM --parquet
        make_once "$D/test-extended" "$R2D2" trainset --procedural 12 --sky extended --seed 910000 $SIM --parquet
        make_once "$D/test-extended-fwhm2" "$R2D2" trainset --procedural 12 --sky extended --seed 910000 --truth-fwhm-px 2 $SIM --parquet
    fi
    TRAIN=("$D/train-radio" "$D/train-extended" "$D/train-extended-more" "$D/train-images")
    VAL=("$D/val-classic" "$D/val-extended")
    # --loss-projection none: with the reference's clipped loss network 1 died on these data
    # (outputs negative everywhere after the first epochs, no gradient, validation 0 dB).
    # Sized for a GPU (training/README.md): on 2 CPU cores it takes about a day, resuming as it
    # goes. Networks 1-14 (the stopping rule rejected a 15th); then STAGE2.
    # Every stage: bias-free U-Nets on 2 crops of 256 a sample and epoch, batches of 8.
    CROPS="--norm none --crop 256 --crops-per-sample 2 --batch 8"
    ARGS="$CROPS --epochs-first 40 --epochs 12 --max-networks 14 --loss-projection none"
    # Networks 15..: the leaky-clipped loss, which clears the empty sky the unclipped loss
    # leaves specked (training/README.md), 4 epochs each, on the 80 classic training skies and
    # 40 extended ones smoothed to a resolution of 1.5..3 pixels (as in vla-r2d2-512's stage
    # 2: skies as generated hold texture finer than the data measure), validated on the
    # classic and 8 smoothed extended skies.
    RESOLVED="--truth-fwhm-px 1.5..3"
    make_once "$D/train-extended-resolved" "$R2D2" trainset --procedural 40 --sky extended --seed 200000 $RESOLVED $SIM
    make_once "$D/val-extended-resolved" "$R2D2" trainset --procedural 8 --sky extended --seed 510000 $RESOLVED $SIM
    STAGE2_TRAIN=("$D/train-radio" "$D/train-extended-resolved")
    STAGE2_VAL=("$D/val-classic" "$D/val-extended-resolved")
    STAGE2="$CROPS --loss-projection leaky --limit-train 120 --epochs 4 --max-networks ${STAGE2_NETWORKS:-17}"
    # Stage 3 (networks 18..): the same data, 8 epochs a network, as vla-r2d2-512's stage 3.
    STAGE3="$CROPS --loss-projection leaky --limit-train 120 --epochs 8 --max-networks ${STAGE3_NETWORKS:-21}"
    ;;
*) echo "unknown recipe $RECIPE (vla-r2d2-512, meerkat-r2d2-512, vla-r2d2-512-broad or vla-r2d2-128)" >&2; exit 2 ;;
esac
# train WORK OPTIONS...: one training stage of the recipe into $SERIES.
train() {
    local work=$1; shift
    $RUN python3 training/train.py --train "${TRAIN[@]}" --val "${VAL[@]}" --series "$SERIES" --work "$work" \
        --name "$RECIPE" --seed 1 --threads "${THREADS:-2}" "$@" ${TRAIN_ARGS:-}
}
RESUME=""
[ -f "$SERIES/manifest.yaml" ] && RESUME="--resume"
train "${WORK:-$D/work}" $ARGS $RESUME
if [ -n "${STAGE2:-}" ]; then
    # A stage may train and validate on sets of its own.
    [ -z "${STAGE2_TRAIN:-}" ] || TRAIN=("${STAGE2_TRAIN[@]}")
    [ -z "${STAGE2_VAL:-}" ] || VAL=("${STAGE2_VAL[@]}")
    # Stages 3 and 4 go on from stage 2 on its sets, in its work directory (its replay cache).
    for stage in "$STAGE2" "${STAGE3:-}" "${STAGE4:-}"; do
        [ -z "$stage" ] || train "${WORK:-$D/work}-stage2" $stage --resume
    done
fi
# train_stage K: the recipe's stage K (options STAGEK) on its own sets (STAGEK_TRAIN,
# STAGEK_VAL), in its own work directory (its replay cache); nothing where the recipe has none.
train_stage() {
    local options="STAGE$1" train_sets="STAGE$1_TRAIN[@]" val_sets="STAGE$1_VAL[@]"
    [ -n "${!options:-}" ] || return 0
    TRAIN=("${!train_sets}")
    VAL=("${!val_sets}")
    train "${WORK:-$D/work}-stage$1" ${!options} --resume
}
train_stage 5
# The 512 series run with the orientation cycle, chosen on their validation sets after their
# networks were trained (training/README.md, "Orientation cycle"); from here on `train.py
# --resume` validates new networks turned as the engine runs them.
case "$RECIPE" in
*-512|*-512-broad)
    grep -q '^orientation_cycle:' "$SERIES/manifest.yaml" ||
        sed -i 's/^normalisation: mean$/&\norientation_cycle: [identity, mirror_x, mirror_y, rotate_180, transpose, rotate_90, rotate_270, anti_transpose]/' "$SERIES/manifest.yaml"
    ;;
esac
# Stages 6-9 were trained after the cycle was written: their replay and validation run the series
# turned, as the engine runs it.
if [ -n "${STAGE6:-}" ]; then
    train_stage 6
    train_stage 7
    train_stage 8
    train_stage 9
    # Every network of stages 5-9 raised validation: the engine runs them all (its early stop
    # would end most skies at network 28).
    N=$(python3 -c 'import sys, yaml; print(len(yaml.safe_load(open(sys.argv[1]))["networks"]))' "$SERIES/manifest.yaml")
    sed -i "s/^early_stop_from: [0-9]*/early_stop_from: $N/" "$SERIES/manifest.yaml"
fi
[ "${EVAL:-1}" = 0 ] || $RUN python3 training/evaluate.py --series "$SERIES" --test "$D/test" --r2d2 "$R2D2" --out "$D/eval" --update-manifest
