#!/usr/bin/env bash
# Campaign 30's leg D (campaigns/c30/rules.txt): leg A with the tonemapped_l2 weight 16x (512).
set -euo pipefail
cd "$(dirname "$0")/../.."
RUN=runs/refine_c30d TAG=d_ REPORT=reports/c30d_valscenes \
  LOSS="smape+0.05*relmse_in+0.05*relmse_in_wide+512*tonemapped_l2" exec bash campaigns/c30/leg_a.sh
