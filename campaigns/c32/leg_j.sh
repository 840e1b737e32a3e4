#!/usr/bin/env bash
# Campaign 32's leg J (campaigns/c32/rules.txt), report only: campaign 31's leg F (the shipped
# refine-layer_medium_ctx) trained again with --seed 1, then leg H's checks against the shipped file.
# Leg K: SEED=2 LEG=k bash campaigns/c32/leg_j.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c32/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
SEED=${SEED:-1} LEG=${LEG:-j}
RUN=runs/refine_c32$LEG INIT=campaigns/c30/refine_ctx_init.safetensors SHIPPED=refine-layer_medium_ctx
[ -e "$INIT" ] || $PY scripts/refine_init.py layer-medium "$INIT" --preset layer_medium_ctx
/usr/bin/time -v $MC train --model refine --preset layer_medium_ctx \
  --init "$INIT" --data data/plain_ref,data/detail_ref,data/detail_ref2 --val-data data/plain_ref --out "$RUN" \
  --steps 800 --batch 8 --crop 96 --lr 1e-3 --loss "smape+0.05*relmse_in+0.05*relmse_in_wide+512*tonemapped_l2" \
  --target reference --spp 4 16 --val-every 200 --val-images 8 --checkpoint-every 50 --workers 1 --threads 2 --seed $SEED \
  --no-progress $( [ -d "$RUN" ] && echo --resume ) > $L/${LEG}_train.log 2>&1
$PY scripts/consistency_probe.py "${HELD[@]}" --models $SHIPPED "$RUN" layer-medium --spp 4 8 16 --ks 4 > $L/${LEG}_probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models $SHIPPED "$RUN" --spp 4 --summary > $L/${LEG}_brightness.log 2>&1
$MC eval --models layer-medium $SHIPPED "$RUN" --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out reports/c32${LEG}_valscenes > $L/${LEG}_eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py reports/c32${LEG}_valscenes/results.json $SHIPPED refine_c32$LEG --per-scene > $L/${LEG}_compare.log 2>&1
echo "leg $LEG done $(date -u +%FT%TZ)" >> $L/${LEG}_train.log
