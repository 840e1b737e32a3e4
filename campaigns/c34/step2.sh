#!/usr/bin/env bash
# Campaign 34's step 2 checks (campaigns/c34/rules.txt), after campaigns/c34/leg_d.sh: both candidates (the run and its
# 0.25 average) against the shipped layer-medium on the 46 held-out images, darkening, the third-party renderings (seeds
# 7-12) with the control campaigns/c27/layer_m27p beside them, the procedural test split and the wide-lens val images.
# Step 4: LEG=s VAL=data/studio_ref bash campaigns/c34/step2.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
LEG=${LEG:-d} VAL=${VAL:-data/dof_ref}
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c34/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
# The runs train without the clamp (as their init, campaigns/c20/layer_m20d); the shipped file clamps with k 4: each
# candidate and the control get the shipped file's setting (tensors untouched).
rc() { $PY scripts/reconfigure_weights.py "$1" "$2" --keep-step --set consistency=4; }
rc runs/layer_m34$LEG/model.safetensors runs/c34/m34${LEG}_k4.safetensors
rc runs/c34/avg_m34${LEG}_25.safetensors runs/c34/avg_m34${LEG}_25_k4.safetensors
rc campaigns/c27/layer_m27p/model.safetensors runs/c34/m27p_k4.safetensors
RUN=runs/c34/m34${LEG}_k4.safetensors AVG=runs/c34/avg_m34${LEG}_25_k4.safetensors CTRL=runs/c34/m27p_k4.safetensors
$PY scripts/consistency_probe.py "${HELD[@]}" --models layer-medium $RUN $AVG --spp 4 8 16 --ks 4 > $L/${LEG}_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium $RUN $AVG --spp 4 --summary > $L/${LEG}_brightness.log 2>&1
$MC eval --models layer-medium $RUN $AVG $CTRL --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high \
  --threads 2 --no-html --no-progress --out reports/c34${LEG}_valscenes > $L/${LEG}_eval_valscenes.log 2>&1
for NEW in m34${LEG}_k4 avg_m34${LEG}_25_k4 m27p_k4; do
  $PY scripts/compare_on_valscenes.py reports/c34${LEG}_valscenes/results.json layer-medium $NEW --per-scene > $L/${LEG}_compare_$NEW.log 2>&1
done
$MC eval --models layer-medium $RUN $AVG --data data/test --threads 1 --spp 4 8 16 --out reports/c34${LEG}_test --no-classic \
  --no-oidn --no-progress --no-html > $L/${LEG}_test.log 2>&1
$MC eval --models layer-medium $RUN $AVG $CTRL --data $VAL --split val --spp 4 8 16 --no-classic --oidn high \
  --threads 1 --no-html --no-progress --out reports/c34${LEG}_val > $L/${LEG}_val.log 2>&1
$PY scripts/ratio_by_lighting.py reports/c34${LEG}_val/results.json layer-medium m34${LEG}_k4 avg_m34${LEG}_25_k4 m27p_k4 --all \
  > $L/${LEG}_val_ratio.log 2>&1
echo "step 2 checks done $(date -u +%FT%TZ)" >> $L/${LEG}_probe.log
