#!/usr/bin/env bash
# Campaign 35's leg A35 (campaigns/c35/rules.txt, step 2): campaign 30's leg A recipe with studio_plain added to the
# head's data, then campaign 29's checks, then studio_plain's val split. SEED=1 RUN=... CHECKS=0 for step 3's members.
set -euo pipefail
cd "$(dirname "$0")/../.."
SEED=${SEED:-0}; RUN=${RUN:-runs/refine_c35a}; TAG=${TAG:-a_}; L=campaigns/c35/logs
if [ "${CHECKS:-1}" = 1 ]; then
  DATA=data/plain_ref,data/detail_ref,data/studio_plain SEED=$SEED RUN=$RUN L=$L TAG=$TAG \
    REPORT=reports/c35${TAG%_}_valscenes bash campaigns/c30/leg_a.sh
  bash campaigns/c35/studio_val.sh "$RUN" "$TAG"
else
  # Training only: the leg driver's first command, nothing after it.
  .venv/bin/mcdenoise train --model refine --preset layer_medium_ctx --init campaigns/c30/refine_ctx_init.safetensors \
    --data data/plain_ref,data/detail_ref,data/studio_plain --val-data data/plain_ref --out "$RUN" --steps 800 --batch 8 \
    --crop 96 --lr 1e-3 --loss smape+0.05*relmse_in+0.05*relmse_in_wide+32*tonemapped_l2 --target reference --spp 4 16 \
    --val-every 200 --val-images 8 --checkpoint-every 50 --workers 1 --threads 2 --seed "$SEED" --no-progress \
    $( [ -d "$RUN" ] && echo --resume ) > $L/${TAG}train.log 2>&1
fi
