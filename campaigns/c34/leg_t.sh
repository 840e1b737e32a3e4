#!/usr/bin/env bash
# Campaign 34, step 5 (campaigns/c34/rules.txt; report only): layer-medium from the shipped weights on the studio set and
# plain_ref only (no small emitters), 500 steps at lr 2e-4, step 2's settings otherwise; then the checks on studio_plain's
# val split and the third-party renderings, both with the shipped clamp (k 4).
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=.venv/bin/mcdenoise PY=.venv/bin/python L=campaigns/c34/logs RUN=runs/layer_m34t
ARGS=(--model layer --preset medium --init campaigns/c20/layer_m20d/model.safetensors
      --data data/studio_plain,data/plain_ref --val-data data/studio_plain
      --steps 500 --batch 8 --crop 96 --lr 2e-4 --loss 'smape+0.05*relmse_in+0.05*relmse_in_wide'
      --branch-fraction 0 --amp bf16 --workers 1 --threads 2 --val-every 250 --checkpoint-every 50 --spp 4 16
      --seed 0 --no-progress)
if [ -f "$RUN/config.json" ]; then "$MC" train --out "$RUN" --resume; else "$MC" train --out "$RUN" "${ARGS[@]}"; fi
mkdir -p runs/c34
$PY scripts/reconfigure_weights.py $RUN/model.safetensors runs/c34/m34t_k4.safetensors --keep-step --set consistency=4
$MC eval --models layer-medium runs/c34/m34t_k4.safetensors --data data/studio_plain --split val --spp 4 8 16 --no-classic \
  --oidn high --threads 1 --no-html --no-progress --out reports/c34t_val > $L/t_val.log 2>&1
$PY scripts/ratio_by_lighting.py reports/c34t_val/results.json layer-medium m34t_k4 --all > $L/t_val_ratio.log 2>&1
$PY scripts/ratio_by_lighting.py reports/c34t_val/results.json oidn-high layer-medium m34t_k4 --all > $L/t_val_oidn.log 2>&1
$MC eval --models layer-medium runs/c34/m34t_k4.safetensors --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high \
  --threads 2 --no-html --no-progress --out reports/c34t_valscenes > $L/t_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c34t_valscenes/results.json layer-medium m34t_k4 --per-scene > $L/t_compare.log 2>&1
echo "step 5 done $(date -u +%FT%TZ)" >> $L/t_val_ratio.log
