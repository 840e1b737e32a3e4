#!/usr/bin/env bash
# Campaign 32's soup FJ (campaigns/c32/rules.txt): the equal average of leg F (the shipped refine-layer_medium_ctx)
# and leg J (the same recipe, seed 1), then the checks of campaigns/c32/checks.sh.
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PY:-.venv/bin/python}; L=campaigns/c32/logs
SOUP=runs/soup_c32fj.safetensors
$PY scripts/average_weights.py "$SOUP" campaigns/c31/refine_c31f campaigns/c32/refine_c32j
bash campaigns/c32/checks.sh "$SOUP" soup
echo "soup done $(date -u +%FT%TZ)" >> $L/soup_compare.log
