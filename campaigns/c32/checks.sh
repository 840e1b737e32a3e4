#!/usr/bin/env bash
# Campaign 32's checks of a candidate against the shipped refine-layer_medium_ctx, the file it would replace
# (campaigns/c32/rules.txt): the held-out probe, the darkening screen, the third-party eval and its comparison.
# Usage: bash campaigns/c32/checks.sh CANDIDATE TAG   (a run folder or .safetensors; TAG names logs and report)
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c32/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
CAND=$1 TAG=$2 SHIPPED=refine-layer_medium_ctx
NAME=$(basename "$CAND" .safetensors)
$PY scripts/consistency_probe.py "${HELD[@]}" --models $SHIPPED "$CAND" layer-medium --spp 4 8 16 --ks 4 > $L/${TAG}_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models $SHIPPED "$CAND" --spp 4 --summary > $L/${TAG}_brightness.log 2>&1
$MC eval --models layer-medium $SHIPPED "$CAND" --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out reports/c32${TAG}_valscenes > $L/${TAG}_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c32${TAG}_valscenes/results.json $SHIPPED "$NAME" --per-scene > $L/${TAG}_compare.log 2>&1
