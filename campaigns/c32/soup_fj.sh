#!/usr/bin/env bash
# Campaign 32's soup FJ (campaigns/c32/rules.txt): the equal average of leg F (the shipped refine-layer_medium_ctx)
# and leg J (the same recipe, seed 1), then leg H's checks against the shipped file.
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c32/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
SOUP=runs/soup_c32fj.safetensors SHIPPED=refine-layer_medium_ctx
$PY scripts/average_weights.py "$SOUP" campaigns/c31/refine_c31f campaigns/c32/refine_c32j
$PY scripts/consistency_probe.py "${HELD[@]}" --models $SHIPPED "$SOUP" layer-medium --spp 4 8 16 --ks 4 > $L/soup_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models $SHIPPED "$SOUP" --spp 4 --summary > $L/soup_brightness.log 2>&1
$MC eval --models layer-medium $SHIPPED "$SOUP" --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out reports/c32soup_valscenes > $L/soup_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c32soup_valscenes/results.json $SHIPPED soup_c32fj --per-scene > $L/soup_compare.log 2>&1
echo "soup done $(date -u +%FT%TZ)" >> $L/soup_compare.log
