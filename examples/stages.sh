# Shared by the staged training scripts (examples/train_*_gns.sh), sourced after they set
# DATA, VALID, RUNS, NET and VALIDATE_EVERY.
#   stage NAME INIT NOISE PUSH STEPS LR LR_FINAL
# trains stage NAME (seed = its number) into $RUNS/NAME from INIT ("-": from scratch) with
# random-walk noise NOISE (m), push-forward PUSH, STEPS steps and a learning rate decaying
# from LR to LR_FINAL; a stage whose model/ exists is skipped, an interrupted one resumes
# from its checkpoint. DRY=1 prints the commands instead of running them.
run() { if [ -n "${DRY:-}" ]; then echo "$@"; else "$@"; fi; }

stage() {
  local out="$RUNS/$1" init=()
  [ "$2" != "-" ] && init=(--init-from "$2")
  if [ -d "$out/model" ]; then echo "stage $1 done ($out/model)"; return; fi
  run diffgns train --data "$DATA" --valid "$VALID" --out "$out" $NET --noise-std "$3" \
    --push-forward "$4" --steps "$5" --lr "$6" --lr-final "$7" --lr-decay-steps "$5" \
    --validate-every "$VALIDATE_EVERY" --seed "${1#s}" "${init[@]}"
}
