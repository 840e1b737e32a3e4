#!/usr/bin/env bash
# Campaign 29's declared ablation: the same stage over kpcn-pixel (a pixel model). Run from the repo root.
set -euo pipefail
MC=.venv/bin/mcdenoise; PY=.venv/bin/python; L=campaigns/c29/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
RUN=runs/refine_kpcn_c29
[ -f campaigns/c29/refine_kpcn_init.safetensors ] || $PY scripts/refine_init.py kpcn-pixel campaigns/c29/refine_kpcn_init.safetensors --preset small
/usr/bin/time -v $MC train --model refine --preset small --init campaigns/c29/refine_kpcn_init.safetensors \
  --data data/plain_ref --val-data data/plain_ref --out "$RUN" --steps 800 --batch 8 --crop 96 --lr 1e-3 \
  --loss "smape+0.05*relmse_in+0.05*relmse_in_wide" --target reference --spp 4 16 --val-every 200 --val-images 8 \
  --checkpoint-every 50 --workers 1 --threads 2 --no-progress $( [ -d "$RUN" ] && echo --resume ) > $L/ablation_train.log 2>&1
$MC eval --models kpcn-pixel "$RUN" --data data/scene_inputs --spp 4 8 16 --no-classic --no-oidn --threads 2 \
  --no-html --no-progress --out reports/c29_ablation > $L/ablation_eval.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c29_ablation/results.json reports/c29_valscenes/results.json kpcn-pixel refine_kpcn_c29 --per-scene > $L/ablation_compare.log 2>&1
$PY scripts/consistency_probe.py "${HELD[@]}" --models kpcn-pixel "$RUN" --spp 4 8 16 --ks 4 > $L/ablation_probe.log 2>&1
echo "ablation done $(date -u +%FT%TZ)" >> $L/ablation_train.log
