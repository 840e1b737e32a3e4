#!/usr/bin/env bash
# Campaign 31's leg E (campaigns/c31/rules.txt): campaign 30's leg C (context features, tonemapped_l2 weight 128)
# with detail_ref2's train split added to the data. Campaign 29's leg driver does the rest.
set -euo pipefail
cd "$(dirname "$0")/../.."
mkdir -p campaigns/c31/logs
RUN=${RUN:-runs/refine_c31e} INIT=campaigns/c30/refine_ctx_init.safetensors PRESET=layer_medium_ctx \
  DATA=data/plain_ref,data/detail_ref,data/detail_ref2 STEPS=800 LR=1e-3 \
  LOSS=${LOSS:-smape+0.05*relmse_in+0.05*relmse_in_wide+128*tonemapped_l2} \
  L=campaigns/c31/logs TAG=${TAG:-e_} REPORT=${REPORT:-reports/c31e_valscenes} exec bash campaigns/c29/leg.sh
