#!/usr/bin/env bash
# Campaign 34's step 2 checks (campaigns/c34/rules.txt), after campaigns/c34/leg_d.sh: both candidates (the run and its
# 0.25 average) against the shipped layer-medium on the 46 held-out images, darkening, the third-party renderings (seeds
# 7-12) with the control campaigns/c27/layer_m27p beside them, the procedural test split and the wide-lens val images.
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c34/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
# The runs train without the clamp (as their init, campaigns/c20/layer_m20d); the shipped file clamps with k 4: each
# candidate and the control get the shipped file's setting (tensors untouched).
rc() { $PY scripts/reconfigure_weights.py "$1" "$2" --keep-step --set consistency=4; }
rc runs/layer_m34d/model.safetensors runs/c34/m34d_k4.safetensors
rc runs/c34/avg_m34d_25.safetensors runs/c34/avg_m34d_25_k4.safetensors
rc campaigns/c27/layer_m27p/model.safetensors runs/c34/m27p_k4.safetensors
RUN=runs/c34/m34d_k4.safetensors AVG=runs/c34/avg_m34d_25_k4.safetensors CTRL=runs/c34/m27p_k4.safetensors
$PY scripts/consistency_probe.py "${HELD[@]}" --models layer-medium $RUN $AVG --spp 4 8 16 --ks 4 > $L/d_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium $RUN $AVG --spp 4 --summary > $L/d_brightness.log 2>&1
$MC eval --models layer-medium $RUN $AVG $CTRL --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high \
  --threads 2 --no-html --no-progress --out reports/c34d_valscenes > $L/d_eval_valscenes.log 2>&1
for NEW in m34d_k4 avg_m34d_25_k4 m27p_k4; do
  $PY scripts/compare_on_valscenes.py reports/c34d_valscenes/results.json layer-medium $NEW --per-scene > $L/d_compare_$NEW.log 2>&1
done
$MC eval --models layer-medium $RUN $AVG --data data/test --threads 1 --spp 4 8 16 --out reports/c34d_test --no-classic \
  --no-oidn --no-progress --no-html > $L/d_test.log 2>&1
$MC eval --models layer-medium $RUN $AVG $CTRL --data data/dof_ref --split val --spp 4 8 16 --no-classic --oidn high \
  --threads 1 --no-html --no-progress --out reports/c34d_dof_val > $L/d_dof_val.log 2>&1
$PY scripts/ratio_by_lighting.py reports/c34d_dof_val/results.json layer-medium m34d_k4 avg_m34d_25_k4 m27p_k4 --all \
  > $L/d_dof_ratio.log 2>&1
echo "step 2 checks done $(date -u +%FT%TZ)" >> $L/d_probe.log
