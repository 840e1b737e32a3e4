#!/usr/bin/env bash
# Campaign 33, step 3's ship (campaigns/c33/rules.txt): the output ensemble of campaign 30's leg A (seed 0) and
# campaign 33's leg L (seed 1) as refine-layer_medium_ctx_x2. Run from the repo root, nothing else running.
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c33/logs
$PY scripts/refine_ensemble.py runs/refine_ens_c33.safetensors campaigns/c30/refine_c30a campaigns/c33/refine_c33l \
  --run runs/refine_ens_c33
$MC eval --models layer-medium runs/refine_ens_c33 --data data/test --threads 1 --spp 4 8 16 --out reports/c33_test_ship \
  --no-classic --oidn high fast --no-progress --no-html > $L/x2_ship_test.log 2>&1
$PY -m mcdenoise.models.ship runs/refine_ens_c33 --eval reports/c33_test_ship/results.json
$PY campaigns/c33/card_x2.py
