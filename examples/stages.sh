# Shared by the staged training scripts (examples/train_*_gns.sh), sourced after they set
# DATA (one or more files, space-separated), VALID, RUNS, NET and VALIDATE_EVERY.
#   stage NAME INIT NOISE PUSH STEPS LR LR_FINAL
# trains stage NAME (seed = its number, or $SEED when set) into $RUNS/NAME from INIT ("-":
# from scratch) with random-walk noise NOISE (m), push-forward PUSH, STEPS steps and a
# learning rate decaying from LR to LR_FINAL; a stage whose model/ exists is skipped, an
# interrupted one resumes from its checkpoint. A stage with no run folder starts from its
# committed checkpoint, checkpoints/<basename of RUNS>/NAME, when there is one (runs/ is lost
# with a checkout; commit a stage's folder there to carry it over). DRY=1 prints the commands instead
# (shell-quoted: one word per argument).
run() { if [ -n "${DRY:-}" ]; then printf '%q ' "$@"; echo; else "$@"; fi; }

stage() {
  local out="$RUNS/$1" init=()
  [ "$2" != "-" ] && init=(--init-from "$2")
  local saved="checkpoints/$(basename "$RUNS")/$1"
  if [ ! -d "$out" ] && [ -d "$saved" ]; then run mkdir -p "$out"; run cp -r "$saved/." "$out/"; fi
  if [ -d "$out/model" ]; then echo "stage $1 done ($out/model)"; return; fi
  run diffgns train --data $DATA --valid "$VALID" --out "$out" $NET --noise-std "$3" \
    --push-forward "$4" --steps "$5" --lr "$6" --lr-final "$7" --lr-decay-steps "$5" \
    --validate-every "$VALIDATE_EVERY" --seed "${SEED:-${1#s}}" "${init[@]}"
}
