#!/usr/bin/env bash
# Campaign 30's leg A (campaigns/c30/rules.txt): the context features and the tonemapped_l2 term, on plain_ref
# and detail_ref, from a fresh head over the shipped layer-medium. Campaign 29's leg driver does the rest.
set -euo pipefail
cd "$(dirname "$0")/../.."
mkdir -p campaigns/c30/logs
RUN=${RUN:-runs/refine_c30a} INIT=${INIT:-campaigns/c30/refine_ctx_init.safetensors} PRESET=${PRESET:-layer_medium_ctx} \
  DATA=${DATA:-data/plain_ref,data/detail_ref} STEPS=800 LR=1e-3 \
  LOSS=${LOSS:-smape+0.05*relmse_in+0.05*relmse_in_wide+32*tonemapped_l2} \
  L=${L:-campaigns/c30/logs} TAG=${TAG:-a_} REPORT=${REPORT:-reports/c30a_valscenes} exec bash campaigns/c29/leg.sh
