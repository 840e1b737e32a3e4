#!/usr/bin/env bash
# Campaign 33's step 1 (campaigns/c33/rules.txt): campaign 30's leg A file checked, on this CPU, against layer-medium
# and the shipped refine-layer_medium_ctx: held-out probe and darkening, third-party eval over seeds 7-12, procedural test.
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c33/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
CAND=campaigns/c30/refine_c30a
$PY scripts/consistency_probe.py "${HELD[@]}" --models layer-medium refine-layer_medium_ctx $CAND --spp 4 8 16 --ks 4 > $L/a_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium $CAND --spp 4 --summary > $L/a_brightness.log 2>&1
$MC eval --models layer-medium refine-layer_medium_ctx $CAND --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high \
  --threads 2 --no-html --no-progress --out reports/c33a_valscenes > $L/a_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c33a_valscenes/results.json refine-layer_medium_ctx refine_c30a --per-scene > $L/a_compare_shipped.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c33a_valscenes/results.json layer-medium refine_c30a --per-scene > $L/a_compare.log 2>&1
$MC eval --models layer-medium $CAND --data data/test --threads 1 --spp 4 8 16 --out reports/c33a_test --no-classic \
  --no-oidn --no-progress --no-html > $L/a_test.log 2>&1
echo "step 1 done $(date -u +%FT%TZ)" >> $L/a_probe.log
