#!/usr/bin/env bash
# Campaign 33's step 4 (campaigns/c33/rules.txt, report only): the three-head ensemble of the W-32 recipe's seeds 0, 1
# and 2, checked against refine-layer_medium_ctx_x2 (the file it would replace) by the standing replacement rule.
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c33/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
CAND=runs/refine_ens3_c33.safetensors SHIPPED=refine-layer_medium_ctx_x2
$PY scripts/refine_ensemble.py $CAND campaigns/c30/refine_c30a campaigns/c33/refine_c33l campaigns/c33/refine_c33m --preset layer_medium_ctx_x3
$PY scripts/consistency_probe.py "${HELD[@]}" --models $SHIPPED $CAND layer-medium --spp 4 8 16 --ks 4 > $L/x3_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models $SHIPPED $CAND --spp 4 --summary > $L/x3_brightness.log 2>&1
$MC eval --models $SHIPPED $CAND --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out reports/c33x3_valscenes > $L/x3_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c33x3_valscenes/results.json $SHIPPED refine_ens3_c33 --per-scene > $L/x3_compare.log 2>&1
$MC eval --models $SHIPPED $CAND --data data/test --threads 1 --spp 4 8 16 --out reports/c33x3_test --no-classic \
  --no-oidn --no-progress --no-html > $L/x3_test.log 2>&1
echo "step 4 done $(date -u +%FT%TZ)" >> $L/x3_probe.log
