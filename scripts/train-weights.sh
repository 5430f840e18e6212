#!/usr/bin/env bash
# The shipped networks' recipe from scratch (docs/models.md): data sets → denoiser stages →
# error network → post-training settings. Every step is a renderloop command; run it from the
# repository root with the venv active (`make setup; source .venv/bin/activate`).
#
#   scripts/train-weights.sh            # the recipe (resumable: finished data and stages are kept)
#   scripts/train-weights.sh --smoke    # the same commands on 2 scenes of 16² and 2 steps each
#   DRY_RUN=1 scripts/train-weights.sh  # print the commands only
#
# Variables: DATA=datasets  OUT=out/recipe (--smoke: out/smoke/datasets, out/smoke). It writes $OUT/final/{denoiser,error_predictor}.pt, a
# --weights folder. The denoiser carries DenoiserConfig's post-training settings (chosen on
# scenes/val for the shipped weights); the error network is calibrated on scenes/val last.
# Shipping is a copy into models/weights/ after `renderloop bench --denoiser --suite dev
# --weights $OUT/final` beats the shipped weights there.
set -euo pipefail

MODE=full
case "${1:-}" in
  "") ;;
  --smoke) MODE=smoke ;;
  *) echo "train-weights: unknown argument '$1' (--smoke or nothing)" >&2; exit 2 ;;
esac
if [ "$MODE" = full ]; then DATA=${DATA:-datasets}; OUT=${OUT:-out/recipe}
else DATA=${DATA:-out/smoke/datasets}; OUT=${OUT:-out/smoke}; fi
DENOISER_RECIPE=kpcn-single-frame-oidn
ERROR_RECIPE=error-spp-disagreement

run() {
  echo "+ $*"
  if [ -z "${DRY_RUN:-}" ]; then "$@"; fi
}

# scenes SIZE REFERENCE_SPP STEPS: the full recipe's, or the smoke run's tiny ones
if [ "$MODE" = full ]; then
  scenes() { echo "$1"; }; SIZE=128; spp() { echo "$1"; }; steps() { echo "$1"; }
  FIT=(--batch 8 --crop 64 --quiet --resume)
else
  scenes() { echo 2; }; SIZE=16; spp() { echo 64; }; steps() { echo 2; }
  FIT=(--batch 2 --crop 16 --quiet)
fi
dataset() {  # OUT_NAME SCENES SEED REFERENCE_SPP [more dataset flags]
  local name=$1 n=$2 seed=$3 reference=$4; shift 4
  run renderloop dataset -o "$DATA/$name" --scenes "$(scenes "$n")" --size "$SIZE" --frames 1 --seed "$seed" \
    --split train --reference-spp "$(spp "$reference")" --quiet "$@"
}
train() {  # STAGE OUT STEPS LR VAL_EVERY [more train flags]
  local stage=$1 out=$2 n=$3 lr=$4 every=$5; shift 5
  local val=$every; [ "$MODE" = smoke ] && val=1
  run renderloop train --stage "$stage" -o "$out" --steps "$(steps "$n")" --lr "$lr" --val-every "$val" "${FIT[@]}" "$@"
}

# 1. The denoiser's data: 400 procedural scenes (rooms and ground planes, mixed materials) and
#    40 rooms lit only by a tiny bulb inside a lampshade (fireflies), single frames.
dataset ens128 400 0 512
dataset shaded128 40 11 2048 --layout shaded
DENOISER_DATA=(--data "$DATA/ens128" --data "$DATA/shaded128" --recipe "$DENOISER_RECIPE")

# 2. The denoiser (Vogels et al. 2018's stages on the shipped configuration: single frame, OIDN
#    candidate in the joint softmax and read by the trunk): one pyramid level, then all three and
#    the compositor, then the candidate's gate alone, then the λ directions alone. Each stage
#    starts from the previous file; λ = 1 until the last.
train single "$OUT/single" 4000 1e-3 500 "${DENOISER_DATA[@]}"
train multiscale "$OUT/multiscale" 10000 5e-4 500 "${DENOISER_DATA[@]}" --init "$OUT/single/stage_single.pt"
train gate "$OUT/gate" 1200 3e-3 200 "${DENOISER_DATA[@]}" --init "$OUT/multiscale/stage_multiscale.pt"
train lambda "$OUT/final" 1500 1e-3 250 "${DENOISER_DATA[@]}" --init "$OUT/gate/stage_gate.pt"

# 3. The error network learns the error of the loop's own inputs (`--loop-branch`: the 16-spp
#    buffer continued by the loop's allocator), which needs an error network to allocate with:
#    a first one on the uniform/adaptive levels of the denoiser's data drives those builds.
run mkdir -p "$OUT/bootstrap"
run cp "$OUT/final/denoiser.pt" "$OUT/bootstrap/denoiser.pt"
train error "$OUT/bootstrap" 3000 1e-3 500 "${DENOISER_DATA[@]}"
dataset loop128r4k 97 0 4096 --loop-branch --weights "$OUT/bootstrap"
dataset window128 60 7 4096 --loop-branch --layout window --weights "$OUT/bootstrap"
train error "$OUT/final" 5000 1e-3 500 --data "$DATA/loop128r4k" --data "$DATA/window128" \
  --recipe "$ERROR_RECIPE" --error-levels spp16,loop32,loop64,loop128

# 4. Post-training settings. The denoiser's (gate offsets, caps, kernel clamp, energy, albedo
#    floor) were written by its last stage. The error network's calibration (output and change
#    scale) is fitted on the nine validation scenes; the smoke run's networks are not worth it.
if [ "$MODE" = full ]; then
  run renderloop bench --calibration --suite val --weights "$OUT/final" --fit-scale "$OUT/final"
fi
