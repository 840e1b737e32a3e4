#!/usr/bin/env bash
# Campaign 35's leg U35 (campaigns/c35/rules.txt, step 5): leg S35's recipe (the spread features) with studio_plain and
# dof_ref, which the shipped base never trained on, added to the data; campaign 29's checks, studio_plain's val split
# and the bias/variance split on the third-party renderings. Resumes runs/refine_c35u when present.
set -euo pipefail
cd "$(dirname "$0")/../.."
INIT=campaigns/c35/refine_spread_init.safetensors
[ -e $INIT ] || .venv/bin/python scripts/refine_init.py layer-medium $INIT --preset layer_medium_ctx_spread
DATA=data/plain_ref,data/detail_ref,data/studio_plain,data/dof_ref RUN=runs/refine_c35u INIT=$INIT \
  PRESET=layer_medium_ctx_spread L=campaigns/c35/logs TAG=u_ REPORT=reports/c35u_valscenes bash campaigns/c30/leg_a.sh
bash campaigns/c35/studio_val.sh runs/refine_c35u u_
.venv/bin/python scripts/bias_variance_probe.py data/scene_inputs/*spp16_seed* --spp 4 \
  --models runs/refine_c35s runs/refine_c35u > campaigns/c35/logs/u_bias_variance.log 2>&1
