#!/usr/bin/env bash
# Campaign 35's leg V35 (campaigns/c35/rules.txt, step 6): leg S35's recipe (spread features, leg A's data, the same
# init, seed 0) with the input spp drawn from 2-16 instead of 4-16. Below 4 spp the shipped base (trained on 4-16)
# leaves noise on images it has fitted, so the head meets, in training, the residual noise it leaves on unfamiliar
# content at 4 spp. Campaign 29's checks, S35's studio val comparison and the bias/variance split.
# Resumes runs/refine_c35v when present.
set -euo pipefail
cd "$(dirname "$0")/../.."
INIT=campaigns/c35/refine_spread_init.safetensors
[ -e $INIT ] || .venv/bin/python scripts/refine_init.py layer-medium $INIT --preset layer_medium_ctx_spread
RUN=runs/refine_c35v INIT=$INIT PRESET=layer_medium_ctx_spread SPP="2 16" L=campaigns/c35/logs TAG=v_ \
  REPORT=reports/c35v_valscenes bash campaigns/c30/leg_a.sh
bash campaigns/c35/studio_val.sh runs/refine_c35v v_
.venv/bin/python scripts/bias_variance_probe.py data/scene_inputs/*spp16_seed* --spp 4 \
  --models runs/refine_c35s runs/refine_c35v > campaigns/c35/logs/v_bias_variance.log 2>&1
