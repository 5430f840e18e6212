#!/usr/bin/env bash
# The denoiser's training recipe as one script: render its training data, then fine-tune the
# shipped network on it. Every step is a renderloop command; run it from the repository root
# with the venv active (`make setup; source .venv/bin/activate`).
#
#   scripts/train-weights.sh            # run it (resumable: finished data and stages are kept)
#   DRY_RUN=1 scripts/train-weights.sh  # print the commands only
#
# Variables:
#   PROFILE=cpu  2-core CPU: about 65 min as measured (docs/training-recipe.md)
#   PROFILE=gpu  the same steps scaled for a CUDA machine: 10x the scenes, 4x the steps, batch 32;
#                the renderer picks cuda_ad_rgb by itself where a GPU works
#                (service/render/runtime.py). Never run yet: no session has been lent a GPU.
#   DATA=datasets  OUT=out/recipe  INIT=models/weights/denoiser.pt (the network it fine-tunes,
#                  and where the post-training settings come from)
#
# It writes $OUT/final/denoiser.pt. Shipping it is a copy into models/weights/, after it has been
# compared with the shipped weights on the validation scenes (`python -m
# bench.experiments.gate_offset --suite val --weights $OUT/final`) and measured once on the suite
# (`renderloop bench --denoiser --suite dev --weights $OUT/final`). Its one CPU run tied on both,
# so the shipped weights are still the chain their checkpoint records (docs/training-recipe.md).
# The error network is not retrained here: its data (docs/error-network.md) takes another 80 CPU
# minutes.
set -euo pipefail

PROFILE=${PROFILE:-cpu}
DATA=${DATA:-datasets}
OUT=${OUT:-out/recipe}
INIT=${INIT:-models/weights/denoiser.pt}

case "$PROFILE" in
  cpu) SCALE=1; STEP_SCALE=1; BATCH=8 ;;
  gpu) SCALE=10; STEP_SCALE=4; BATCH=32 ;;
  *) echo "train-weights: PROFILE must be cpu or gpu, got '$PROFILE'" >&2; exit 2 ;;
esac

run() {
  echo "+ $*"
  if [ -z "${DRY_RUN:-}" ]; then "$@"; fi
}

# 1. Data (each build resumes where it stopped; the seeds are the shipped data's).
run renderloop dataset -o "$DATA/ens128" --scenes $((400 * SCALE)) --size 128 --frames 1 --seed 0 --split train \
  --reference-spp 512
run renderloop dataset -o "$DATA/shaded128" --scenes $((40 * SCALE)) --size 128 --frames 1 --seed 11 --split train \
  --reference-spp 2048 --loop-branch --layout shaded
run renderloop dataset -o "$DATA/window128d" --scenes $((60 * SCALE)) --size 128 --frames 1 --seed 7 --split train \
  --reference-spp 1024 --layout window

# --resume: a stage stopped part-way continues from its saved state, and a finished one only
# writes its checkpoint's settings again (a best-so-far checkpoint exists long before the end).
TRAIN=(--data "$DATA/ens128" --data "$DATA/shaded128" --data "$DATA/window128d"
       --oidn-candidate --single-frame --candidate-features --batch "$BATCH" --crop 64 --resume --quiet)

# 2. Every weight at λ = 1 (trunk, kernels, gate, compositor), from the shipped network.
run renderloop train "${TRAIN[@]}" --stage multiscale --init "$INIT" --keep-settings -o "$OUT/multiscale" \
  --steps $((8000 * STEP_SCALE)) --val-every 500 --lr 5e-4

# 3. The λ directions again, on the new trunk. Both stages carry $INIT's post-training settings
#    (gate offsets, caps, clamp, energy tolerance: chosen on the validation scenes) through.
run renderloop train "${TRAIN[@]}" --stage lambda --init "$OUT/multiscale/stage_multiscale.pt" --keep-settings \
  -o "$OUT/final" --steps $((1500 * STEP_SCALE)) --val-every 250 --lr 1e-3

# The shipped error network beside it, so the folder is a whole --weights directory.
run cp models/weights/error_predictor.pt "$OUT/final/error_predictor.pt"
