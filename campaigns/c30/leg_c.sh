#!/usr/bin/env bash
# Campaign 30's leg C (campaigns/c30/rules.txt): leg A with the tonemapped_l2 weight 4x (128), the knob toward PSNR.
set -euo pipefail
cd "$(dirname "$0")/../.."
RUN=runs/refine_c30c TAG=c_ REPORT=reports/c30c_valscenes \
  LOSS="smape+0.05*relmse_in+0.05*relmse_in_wide+128*tonemapped_l2" exec bash campaigns/c30/leg_a.sh
