#!/usr/bin/env bash
# Campaign 29's leg and its checks, in order (campaigns/c29/rules.txt). Run from the repo root.
set -euo pipefail
MC=.venv/bin/mcdenoise; PY=.venv/bin/python; L=campaigns/c29/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
RUN=${RUN:-runs/refine_c29}
STEPS=${STEPS:-800}
[ -f campaigns/c29/refine_init.safetensors ] || $PY scripts/refine_init.py layer-medium campaigns/c29/refine_init.safetensors
/usr/bin/time -v $MC train --model refine --preset layer_medium --init campaigns/c29/refine_init.safetensors \
  --data data/plain_ref --val-data data/plain_ref --out "$RUN" --steps "$STEPS" --batch 8 --crop 96 --lr 1e-3 \
  --loss "smape+0.05*relmse_in+0.05*relmse_in_wide" --target reference --spp 4 16 --val-every 200 --val-images 8 \
  --checkpoint-every 50 --workers 1 --threads 2 --no-progress $( [ -d "$RUN" ] && echo --resume ) > $L/train.log 2>&1
$PY scripts/consistency_probe.py "${HELD[@]}" --models layer-medium "$RUN" --spp 4 8 16 --ks 4 > $L/probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium "$RUN" --spp 4 --summary > $L/brightness.log 2>&1
$MC eval --models layer-medium "$RUN" --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out reports/c29_valscenes > $L/eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c29_valscenes/results.json layer-medium "$(basename "$RUN")" --per-scene > $L/compare.log 2>&1
echo "leg done $(date -u +%FT%TZ)" >> $L/train.log
