#!/usr/bin/env bash
# issue 21's column inversion through the GNS: gns_cg16_pfn (issue 4's column model, stage 9)
# fine-tuned through its own rollouts, the unrolled loss that gave the general model its last
# 10% (`diffgns train --unroll K`, docs/guides/gns.md). Stage 9's data (the 36-collapse grid
# and the 12 tall columns, `make -j2 columns16-data`), its noise and learning rates; the loss
# over K frames of the model's own rollout after 3 push-forward frames. Two candidates, one
# per core: K=8 (seed 201) and K=16 (seed 202), selected with benchmarks/gns_select.py on
# the 12 validation collapses (the card's rule). Run niced in the background:
#   STAGE=u8 nohup taskset -c 0 examples/train_column_unroll.sh &> runs/col_u8.log &
#   STAGE=u16 nohup taskset -c 1 examples/train_column_unroll.sh &> runs/col_u16.log &
set -euo pipefail
DATA=${DATA:-"data/columns16_train.h5 data/columns16_tall.h5"}
VALID=${VALID:-data/columns16_valid.h5}
RUNS=${RUNS:-runs/column_unroll}
INIT=${INIT:-src/diffgns/models/gns_cg16_pfn}
BASE="--radius 0.032 --latent 64 --mp-steps 5 --coarse-grain 16 --frame-stride 2 --batch-size 2"
VALIDATE_EVERY=100000
source "$(dirname "$0")/stages.sh"
case "${STAGE:-u8}" in
  u8) NET="$BASE --unroll 8" SEED=201 stage u8 "$INIT" 3.125e-6 3 3000 2.5e-5 2.5e-6 ;;
  u16) NET="$BASE --unroll 16" SEED=202 stage u16 "$INIT" 3.125e-6 3 3000 2.5e-5 2.5e-6 ;;
  *) echo "STAGE must be u8 or u16" >&2; exit 2 ;;
esac
