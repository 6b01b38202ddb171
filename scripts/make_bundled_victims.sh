#!/usr/bin/env bash
# Reproduce the bundled victims from scratch: render the training and held-out sets, train
# both models, evaluate them on the held-out set and write their model cards. CPU only.
#
#   scripts/make_bundled_victims.sh [WORK_DIR] [OUT_DIR]
#   DISTRIBUTION=v2 scripts/make_bundled_victims.sh [WORK_DIR] [OUT_DIR]
#   DISTRIBUTION=v3 scripts/make_bundled_victims.sh [WORK_DIR] [OUT_DIR]
#   DISTRIBUTION=v4 scripts/make_bundled_victims.sh [WORK_DIR] [OUT_DIR]
#
# DISTRIBUTION=v1 (default) makes bundled:classifier, bundled:detector and bundled:yolo (about
# 50 minutes on 2 free cores; the YOLO-style detector alone: 4.2 min on 2 threads, from scratch);
# DISTRIBUTION=v2 makes bundled:classifier-v2 and bundled:detector-v2 (camera height and ground
# distance, every background and weather; about 72 minutes on ONE core: 31 min of renders, 18 min
# for the classifier, 23 min for the detector); DISTRIBUTION=v3 makes bundled:classifier-v3 and
# bundled:detector-v3 (v2 with plain, unsaturated objects too; the same sizes, on ONE core);
# DISTRIBUTION=v4 makes bundled:classifier-v4 only: the v3 data, twice the training renders (16,000,
# rendered as two parts under seeds 0 and 1, one core each; the first part is v3's own set), the same
# held-out set and training as classifier-v3 (trained on 2 threads: 35 min, the renders 40 min on two cores).
# DISTRIBUTION=at makes bundled:classifier-at: bundled:classifier-v3 fine-tuned against attacked textures
# (undream victims train-adversarial) on v3 renders made with --shading: 1600 (seed 0) + 1000 (seed 1)
# training images, one core each, and the first 600 of v3's held-out set.
#
# WORK_DIR (default build/bundled-victims, or build/bundled-victims-v2 / -v3) receives the datasets;
# OUT_DIR (default WORK_DIR/models) the two model folders. Pass OUT_DIR=undream/victims/bundled
# to replace the shipped models. Set UNDREAM to the command that runs undream.
#
# The seeds, sizes, epochs and torch thread counts below are the ones the shipped models
# were made with; with the same library versions on the same kind of CPU they give the
# same weights byte for byte (the thread count changes float summation order, hence the
# weights). Torch slows down badly when given more threads than there are free cores.
# The v2 and v3 models were made on one core (taskset -c 1, OMP_NUM_THREADS=1).
set -euo pipefail

DISTRIBUTION=${DISTRIBUTION:-v1}
case "$DISTRIBUTION" in
    v1) N_TRAIN=4000 N_TEST=800 CLS_EPOCHS=30 DET_EPOCHS=40 SUFFIX= YOLO_EPOCHS=60
        CLS_THREADS=${CLS_THREADS:-2} DET_THREADS=${DET_THREADS:-1} YOLO_THREADS=${YOLO_THREADS:-2} ;;
    v2) N_TRAIN=8000 N_TEST=1200 CLS_EPOCHS=40 DET_EPOCHS=50 SUFFIX=-v2
        CLS_THREADS=${CLS_THREADS:-1} DET_THREADS=${DET_THREADS:-1} ;;
    v3) N_TRAIN=8000 N_TEST=1200 CLS_EPOCHS=40 DET_EPOCHS=50 SUFFIX=-v3
        CLS_THREADS=${CLS_THREADS:-1} DET_THREADS=${DET_THREADS:-1} ;;
    v4) N_TRAIN=8000 N_TEST=1200 CLS_EPOCHS=40 SUFFIX=-v4 CLS_THREADS=${CLS_THREADS:-2} ;;
    at) N_TEST=600 SUFFIX=-at CLS_THREADS=${CLS_THREADS:-2} ;;
    *) echo "DISTRIBUTION must be v1, v2, v3, v4 or at, got '$DISTRIBUTION'" >&2; exit 2 ;;
esac
WORK=${1:-build/bundled-victims${SUFFIX}}
OUT=${2:-$WORK/models}
UNDREAM=${UNDREAM:-undream}

if [ "$DISTRIBUTION" = at ]; then  # v3's data with its shading, in two parts, one core each
    taskset -c 0 $UNDREAM victims make-dataset --out "$WORK/train0" --n 1600 --seed 0 --split train \
        --distribution v3 --shading --no-progress &
    part0=$!
    taskset -c 1 $UNDREAM victims make-dataset --out "$WORK/test" --n "$N_TEST" --seed 0 --split test \
        --distribution v3 --shading --no-progress
    taskset -c 1 $UNDREAM victims make-dataset --out "$WORK/train1" --n 1000 --seed 1 --split train \
        --distribution v3 --shading --no-progress
    wait "$part0"
    $UNDREAM victims train-adversarial --base bundled:classifier-v3 --data "$WORK/train0" --data "$WORK/train1" \
        --test "$WORK/test" --out "$OUT/classifier$SUFFIX" --seed 0 --threads "$CLS_THREADS"
    exit 0
fi

if [ "$DISTRIBUTION" = v4 ]; then  # v3's data in two parts, one core each; classifier only
    taskset -c 0 $UNDREAM victims make-dataset --out "$WORK/train1" --n "$N_TRAIN" --seed 1 --split train \
        --distribution v3 --no-progress &
    part1=$!
    taskset -c 1 $UNDREAM victims make-dataset --out "$WORK/train0" --n "$N_TRAIN" --seed 0 --split train \
        --distribution v3 --no-progress
    taskset -c 1 $UNDREAM victims make-dataset --out "$WORK/test" --n "$N_TEST" --seed 0 --split test \
        --distribution v3 --no-progress
    wait "$part1"  # its exit status: a failed part stops the script (set -e)
    $UNDREAM victims train --task classification --data "$WORK/train0" --data "$WORK/train1" --test "$WORK/test" \
        --out "$OUT/classifier$SUFFIX" --seed 0 --epochs "$CLS_EPOCHS" --threads "$CLS_THREADS"
    $UNDREAM victims evaluate --victim "$OUT/classifier$SUFFIX" --data "$WORK/test"
    exit 0
fi

$UNDREAM victims make-dataset --out "$WORK/train" --n "$N_TRAIN" --seed 0 --split train \
    --distribution "$DISTRIBUTION"
$UNDREAM victims make-dataset --out "$WORK/test" --n "$N_TEST" --seed 0 --split test \
    --distribution "$DISTRIBUTION"

$UNDREAM victims train --task classification --data "$WORK/train" --test "$WORK/test" \
    --out "$OUT/classifier$SUFFIX" --seed 0 --epochs "$CLS_EPOCHS" --threads "$CLS_THREADS"
$UNDREAM victims train --task detection --data "$WORK/train" --test "$WORK/test" \
    --out "$OUT/detector$SUFFIX" --seed 0 --epochs "$DET_EPOCHS" --threads "$DET_THREADS" \
    --backbone "$OUT/classifier$SUFFIX"

if [ "$DISTRIBUTION" = v1 ]; then  # undream's YOLO-style detector, from scratch (no backbone)
    $UNDREAM victims train --task detection --arch yolo --data "$WORK/train" --test "$WORK/test" \
        --out "$OUT/yolo" --seed 0 --epochs "$YOLO_EPOCHS" --threads "$YOLO_THREADS"
fi

# The held-out numbers of the models as saved (overall, per weather, background and camera band).
$UNDREAM victims evaluate --victim "$OUT/classifier$SUFFIX" --data "$WORK/test"
$UNDREAM victims evaluate --victim "$OUT/detector$SUFFIX" --data "$WORK/test"
if [ "$DISTRIBUTION" = v1 ]; then
    $UNDREAM victims evaluate --victim "$OUT/yolo" --data "$WORK/test"
fi
