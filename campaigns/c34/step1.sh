#!/usr/bin/env bash
# Campaign 34, step 1 (campaigns/c34/rules.txt): the shipped models and OIDN 2.5.1 high on the wide-lens held-out
# images (data/dof_ref's val split), and the geometric-mean ratio to OIDN high beside the standing held-out set's.
set -euo pipefail
cd "$(dirname "$0")/../.."
L=campaigns/c34/logs
.venv/bin/mcdenoise eval --models layer-medium kpcn-pixel refine-layer_medium_ctx_x2 ${EXTRA:-} --data data/dof_ref --split val \
  --spp 4 8 16 --no-classic --oidn high --threads 1 --no-html --no-progress --out reports/c34_dof_val | tee $L/step1_eval.log
.venv/bin/python scripts/ratio_by_lighting.py reports/c34_dof_val/results.json oidn-high layer-medium kpcn-pixel \
  refine-layer_medium_ctx_x2 ${EXTRA_NAMES:-} --all | tee $L/step1_ratio.log
.venv/bin/python scripts/ratio_by_lighting.py reports/c32_heldout_bands/results.json oidn-high layer-medium --all \
  | tee $L/step1_heldout_ratio.log
