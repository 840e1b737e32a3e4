#!/usr/bin/env bash
# Campaign 29's leg 2 (campaigns/c29/rules.txt): leg 1's weights, with data/detail_ref's small emitters added.
set -euo pipefail
cd "$(dirname "$0")/../.."
RUN=runs/refine_c29b INIT=runs/refine_c29 DATA=data/plain_ref,data/detail_ref STEPS=200 LR=5e-4 TAG=leg2_ \
  REPORT=reports/c29b_valscenes exec bash campaigns/c29/leg.sh
