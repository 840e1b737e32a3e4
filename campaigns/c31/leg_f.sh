#!/usr/bin/env bash
# Campaign 31's leg F (campaigns/c31/rules.txt): leg E with another tonemapped_l2 weight, W=64 or 512 as the rules
# choose from leg E's held-out result. Usage: W=512 bash campaigns/c31/leg_f.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
: "${W:?set W (64 or 512, campaigns/c31/rules.txt)}"
RUN=runs/refine_c31f TAG=f_ REPORT=reports/c31f_valscenes \
  LOSS="smape+0.05*relmse_in+0.05*relmse_in_wide+${W}*tonemapped_l2" exec bash campaigns/c31/leg_e.sh
