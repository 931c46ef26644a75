#!/usr/bin/env bash
# Staged training of the 3D GNS (issue 24) on the axisymmetric collapses of
# `make -j2 column3d-data` (R0 = 5 cm, 4 cells across R0, 8 particles per cell), the recipe
# that made gns_cg16_pfn in 2D, scaled to 3D:
#   stage 0   from scratch, random-walk noise 3e-4 m, no push-forward     (12,000 steps)
#   stage 1   push-forward 2 at 3e-4 m                                    (3,000 steps)
#   stages 2-5 push-forward 2, noise halved stage by stage 1e-4 -> 1.25e-5 m (3,000 each)
# Nodes: 2 x 2 x 2 MPM particles per node (--coarse-grain 8, 12.5 mm apart), every second
# 2.5 ms frame (--frame-stride 2), radius 0.025 m (two node spacings, ~33 neighbours),
# latent 64, 5 message-passing steps. Resumable: a finished stage (its model/ exists) is
# skipped, an interrupted one resumes from its checkpoint. The held-out test set
# (`make column3d-test-data`) is drawn after the last stage.
# Run niced in the background:
#   nice -n 19 nohup examples/train_column3d_gns.sh &> runs/column3d.log &
# DRY=1 prints the commands without running them.
set -euo pipefail
DATA=${DATA:-data/column3d_train.h5}
VALID=${VALID:-data/column3d_valid.h5}
RUNS=${RUNS:-runs/column3d}
NET=${NET:-"--radius 0.025 --latent 64 --mp-steps 5 --coarse-grain 8 --frame-stride 2 --batch-size 2"}
VALIDATE_EVERY=1500
source "$(dirname "$0")/stages.sh"

stage s0 - 3e-4 0 12000 1e-3 1e-5
stage s1 "$RUNS/s0/model" 3e-4 2 3000 5e-5 5e-6
prev="$RUNS/s1/model"; k=2
for sigma in 1e-4 5e-5 2.5e-5 1.25e-5; do
  stage "s$k" "$prev" "$sigma" 2 3000 5e-5 5e-6
  prev="$RUNS/s$k/model"; k=$((k + 1))
done
