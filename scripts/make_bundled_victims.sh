#!/usr/bin/env bash
# Reproduce the bundled victims (bundled:classifier, bundled:detector) from scratch:
# render the training and held-out sets, train both models, evaluate them on the
# held-out set and write their model cards. CPU only; about an hour on 2 cores.
#
#   scripts/make_bundled_victims.sh [WORK_DIR] [OUT_DIR]
#
# WORK_DIR (default build/bundled-victims) receives the datasets; OUT_DIR (default
# undream/victims/bundled, i.e. the shipped models are replaced) the two model folders.
# Set UNDREAM to the command that runs undream (default: undream).
set -euo pipefail

WORK=${1:-build/bundled-victims}
OUT=${2:-undream/victims/bundled}
UNDREAM=${UNDREAM:-undream}
THREADS=${THREADS:-1}  # more threads than free cores slows torch down badly

# The seeds, sizes and epochs the shipped models were made with.
$UNDREAM victims make-dataset --out "$WORK/train" --n 4000 --seed 0 --split train
$UNDREAM victims make-dataset --out "$WORK/test" --n 800 --seed 0 --split test

$UNDREAM victims train --task classification --data "$WORK/train" --test "$WORK/test" \
    --out "$OUT/classifier" --seed 0 --threads "$THREADS"
$UNDREAM victims train --task detection --data "$WORK/train" --test "$WORK/test" \
    --out "$OUT/detector" --seed 0 --threads "$THREADS" --backbone "$OUT/classifier"

# The held-out numbers of the models as users load them (bundled:… when OUT is the default).
$UNDREAM victims evaluate --victim "$OUT/classifier" --data "$WORK/test"
$UNDREAM victims evaluate --victim "$OUT/detector" --data "$WORK/test"
