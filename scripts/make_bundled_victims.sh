#!/usr/bin/env bash
# Reproduce the bundled victims (bundled:classifier, bundled:detector) from scratch:
# render the training and held-out sets, train both models, evaluate them on the
# held-out set and write their model cards. CPU only; about 45 minutes on 2 free cores.
#
#   scripts/make_bundled_victims.sh [WORK_DIR] [OUT_DIR]
#
# WORK_DIR (default build/bundled-victims) receives the datasets; OUT_DIR (default
# WORK_DIR/models) the two model folders. Pass OUT_DIR=undream/victims/bundled to
# replace the shipped models. Set UNDREAM to the command that runs undream.
#
# The seeds, sizes, epochs and torch thread counts below are the ones the shipped models
# were made with; with the same library versions on the same kind of CPU they give the
# same weights byte for byte (the thread count changes float summation order, hence the
# weights). Torch slows down badly when given more threads than there are free cores.
set -euo pipefail

WORK=${1:-build/bundled-victims}
OUT=${2:-$WORK/models}
UNDREAM=${UNDREAM:-undream}
CLS_THREADS=${CLS_THREADS:-2}
DET_THREADS=${DET_THREADS:-1}

$UNDREAM victims make-dataset --out "$WORK/train" --n 4000 --seed 0 --split train
$UNDREAM victims make-dataset --out "$WORK/test" --n 800 --seed 0 --split test

$UNDREAM victims train --task classification --data "$WORK/train" --test "$WORK/test" \
    --out "$OUT/classifier" --seed 0 --threads "$CLS_THREADS"
$UNDREAM victims train --task detection --data "$WORK/train" --test "$WORK/test" \
    --out "$OUT/detector" --seed 0 --threads "$DET_THREADS" --backbone "$OUT/classifier"

# The held-out numbers of the models as saved.
$UNDREAM victims evaluate --victim "$OUT/classifier" --data "$WORK/test"
$UNDREAM victims evaluate --victim "$OUT/detector" --data "$WORK/test"
