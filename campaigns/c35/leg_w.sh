#!/usr/bin/env bash
# Campaign 35's leg W35 (campaigns/c35/rules.txt, step 9): leg S35's recipe (spread features, leg A's data, the same
# init, seed 0, spp 4-16) with a loss led by the input-guided relMSE terms instead of SMAPE, so that the squared
# error, and with it the base's residual noise, weighs most. Campaign 29's checks, studio val and the bias/variance
# split. Resumes runs/refine_c35w when present.
set -euo pipefail
cd "$(dirname "$0")/../.."
INIT=campaigns/c35/refine_spread_init.safetensors
[ -e $INIT ] || .venv/bin/python scripts/refine_init.py layer-medium $INIT --preset layer_medium_ctx_spread
RUN=runs/refine_c35w INIT=$INIT PRESET=layer_medium_ctx_spread LOSS="0.05*smape+relmse_in+relmse_in_wide+32*tonemapped_l2" \
  L=campaigns/c35/logs TAG=w_ REPORT=reports/c35w_valscenes bash campaigns/c30/leg_a.sh
bash campaigns/c35/studio_val.sh runs/refine_c35w w_
.venv/bin/python scripts/bias_variance_probe.py data/scene_inputs/*spp16_seed* --spp 4 \
  --models runs/refine_c35s runs/refine_c35w > campaigns/c35/logs/w_bias_variance.log 2>&1
