#!/usr/bin/env bash
# Campaign 33's step 1 (campaigns/c33/rules.txt): campaign 30's leg A file checked, on this CPU, against layer-medium
# and the shipped refine-layer_medium_ctx: held-out probe and darkening, third-party eval over seeds 7-12, procedural test.
# Step 3: CAND=runs/refine_ens_c33.safetensors TAG=x2 bash campaigns/c33/step1.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c33/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
CAND=${CAND:-campaigns/c30/refine_c30a} TAG=${TAG:-a}
NAME=$(basename "$CAND" .safetensors)
$PY scripts/consistency_probe.py "${HELD[@]}" --models layer-medium refine-layer_medium_ctx $CAND --spp 4 8 16 --ks 4 > $L/${TAG}_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium $CAND --spp 4 --summary > $L/${TAG}_brightness.log 2>&1
$MC eval --models layer-medium refine-layer_medium_ctx $CAND --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high \
  --threads 2 --no-html --no-progress --out reports/c33${TAG}_valscenes > $L/${TAG}_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c33${TAG}_valscenes/results.json refine-layer_medium_ctx "$NAME" --per-scene > $L/${TAG}_compare_shipped.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c33${TAG}_valscenes/results.json layer-medium "$NAME" --per-scene > $L/${TAG}_compare.log 2>&1
$MC eval --models layer-medium $CAND --data data/test --threads 1 --spp 4 8 16 --out reports/c33${TAG}_test --no-classic \
  --no-oidn --no-progress --no-html > $L/${TAG}_test.log 2>&1
echo "step 1 done $(date -u +%FT%TZ)" >> $L/${TAG}_probe.log
