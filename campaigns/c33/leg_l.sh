#!/usr/bin/env bash
# Campaign 33's leg L (campaigns/c33/rules.txt, step 2, report only): campaign 30's leg A recipe (W 32, plain_ref +
# detail_ref, the same init file) with --seed 1, and campaign 29's checks against layer-medium.
set -euo pipefail
cd "$(dirname "$0")/../.."
SEED=${SEED:-1} RUN=runs/refine_c33l L=campaigns/c33/logs TAG=l_ REPORT=reports/c33l_valscenes exec bash campaigns/c30/leg_a.sh
