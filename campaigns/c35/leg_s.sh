#!/usr/bin/env bash
# Campaign 35's leg S35 (campaigns/c35/rules.txt, step 4): campaign 30's leg A recipe with the spread features
# (preset layer_medium_ctx_spread, its own fresh init), campaign 29's checks, then the bias/variance split on the 54
# third-party renderings beside leg A and OIDN 2.5.1 high.
set -euo pipefail
cd "$(dirname "$0")/../.."
INIT=campaigns/c35/refine_spread_init.safetensors
[ -e $INIT ] || .venv/bin/python scripts/refine_init.py layer-medium $INIT --preset layer_medium_ctx_spread
RUN=runs/refine_c35s INIT=$INIT PRESET=layer_medium_ctx_spread L=campaigns/c35/logs TAG=s_ \
  REPORT=reports/c35s_valscenes bash campaigns/c30/leg_a.sh
.venv/bin/python scripts/bias_variance_probe.py data/scene_inputs/*spp16_seed* --spp 4 \
  --models campaigns/c30/refine_c30a runs/refine_c35s > campaigns/c35/logs/s_bias_variance.log 2>&1
