#!/usr/bin/env bash
# The training chain of the shipped MeshGraphNet meshnet_sweep_wide (issue 23; its model
# card has the table), on the data of `make meshnet-data`, from the shipped meshnet_sweep:
#   wide        sweep_train_wide.h5 (Re 75-250), 2500:0.02:4, lr 1e-4 -> 1e-5
#   wide300     sweep_train_75_300.h5, 2000:0.02:4, lr 1e-4 -> 1e-5
#   wide300n1   the same data, 1500:0.01:4, lr 5e-5 -> 5e-6
#   pf16os      the same data, 700:0.01:4:16 (push-forward 16), Re 75-100 drawn 3x as often
#   pfhi        sweep_train_dense.h5, 500:0.01:4:16, lr 2e-5 -> 5e-6, Re 75-100 3x, only the
#               windows at Re >= 150 pushed (--push-min-re 150)
#   pfhid1      pfhi's recipe plus the continuity term (--divergence-weight 1)
#   pfhid1b     pfhid1 + 250 steps at seed 3
#   avgd1bhi    the uniform weight average of pfhid1b and pfhi: the shipped model
# Every stage is committed as checkpoints/meshnet_<stage>, so the script copies those and
# skips them (a stage whose model/ exists is done; an interrupted one resumes from its
# checkpoint with the same command; SIGTERM writes the checkpoint). DRY=1 prints the commands.
# One core, ~0.9-2.2 s/step (push-forward stages the slow end): ~3 h for the whole chain.
# Run niced in the background:  nice -n 19 nohup examples/train_meshnet_sweep_wide.sh &> runs/meshnet_wide.log &
set -euo pipefail
run() { if [ -n "${DRY:-}" ]; then echo "$@"; else "$@"; fi; }
PY=${PY:-.venv/bin/python}
DIFFGNS=${DIFFGNS:-.venv/bin/diffgns}
NET="--latent 64 --mp-steps 6 --batch-size 2"

stage() {  # stage NAME INIT DATA STAGES LR LR_FINAL SEED [options...]
  local name=$1 init=$2 data=$3 stages=$4 lr=$5 lr_final=$6 seed=$7
  shift 7
  local out="runs/meshnet_$name" saved="checkpoints/meshnet_$name"
  if [ ! -d "$out" ] && [ -d "$saved" ]; then run mkdir -p "$out"; run cp -r "$saved/." "$out/"; fi
  local last=${stages##*,}
  local done_steps
  done_steps=$("$PY" -c "import json; print(json.load(open('$out/model/model.json'))['steps'])" \
    2>/dev/null || echo -1)  # model/ is also written on SIGTERM: done = its steps reached
  if [ "$done_steps" = "${last%%:*}" ]; then echo "stage $name done ($out/model)"; return; fi
  run "$PY" -m diffgns.mesh.stages --data "data/$data" --out "$out" --stages "$stages" $NET \
    --lr "$lr" --lr-final "$lr_final" --checkpoint-every 50 --seed "$seed" --init-from "$init" "$@"
}

stage wide "meshnet_sweep" sweep_train_wide.h5 2500:0.02:4 1e-4 1e-5 0
stage wide300 runs/meshnet_wide/model sweep_train_75_300.h5 2000:0.02:4 1e-4 1e-5 0
stage wide300n1 runs/meshnet_wide300/model sweep_train_75_300.h5 1500:0.01:4 5e-5 5e-6 0
stage pf16os runs/meshnet_wide300n1/model sweep_train_75_300.h5 700:0.01:4:16 5e-5 5e-6 1 \
  --oversample-re 75-100:3
LAST=(--oversample-re 75-100:3 --push-min-re 150)
stage pfhi runs/meshnet_pf16os/model sweep_train_dense.h5 500:0.01:4:16 2e-5 5e-6 2 "${LAST[@]}"
stage pfhid1 runs/meshnet_pf16os/model sweep_train_dense.h5 500:0.01:4:16 2e-5 5e-6 2 \
  "${LAST[@]}" --divergence-weight 1
stage pfhid1b runs/meshnet_pfhid1/model sweep_train_dense.h5 250:0.01:4:16 2e-5 5e-6 3 \
  "${LAST[@]}" --divergence-weight 1
if [ -d runs/meshnet_avgd1bhi/model ]; then echo "avgd1bhi done (runs/meshnet_avgd1bhi/model)"
else run "$DIFFGNS" average runs/meshnet_pfhid1b/model runs/meshnet_pfhi/model \
  --out runs/meshnet_avgd1bhi/model; fi
