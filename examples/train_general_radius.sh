#!/usr/bin/env bash
# The general GNS's stages s0 and s1 (r1's recipe of examples/train_general_gns.sh) with
# another connectivity radius, to measure what the radius does alone (docs/guides/gns.md,
# "The connectivity radius"): R=0.022 -> runs/general_r22 (stage s0 committed under
# checkpoints/general_r22/s0), R=0.040 -> runs/general_r40 (stage s0 finished on
# 2026-12-07 after a resume at step 22,216, committed under checkpoints/general_r40/s0: this
# script goes on with s1). Seeds: 121/122 for 0.022, 51/61 (r1's and r1b's) for 0.040.
# Run niced in the background:  RADIUS=0.040 nohup examples/train_general_radius.sh &> runs/r40.log &
set -euo pipefail
RADIUS=${RADIUS:-0.040}
TAG=$(printf 'r%02d' "$(python3 -c "print(round(1000 * $RADIUS))")")
DATA=${DATA:-data/granular_train.h5}
VALID=${VALID:-data/granular_valid.h5}
RUNS=${RUNS:-runs/general_$TAG}
NET="--radius $RADIUS --latent 64 --mp-steps 5 --coarse-grain 16 --frame-stride 1 --batch-size 2 \
 --obstacle-features --pad-nodes 32 --mirror 0.5 --target-scale-floor 1"
VALIDATE_EVERY=100000
source "$(dirname "$0")/stages.sh"
if [ "$TAG" = r22 ]; then S0=121; S1=122; else S0=51; S1=61; fi
SEED=$S0 stage s0 - 1e-4 2 36000 1e-3 1e-5
SEED=$S1 stage s1 "$RUNS/s0/model" 5e-5 2 30000 3e-4 1e-5
