#!/usr/bin/env bash
# A campaign-29 leg and its checks, in order (campaigns/c29/rules.txt). Run from the repo root.
# The defaults are leg 1; leg2.sh sets the variables for leg 2, campaigns/c30/leg_*.sh for campaign 30's legs
# (PRESET, LOSS and L, the log folder, too).
set -euo pipefail
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=${L:-campaigns/c29/logs}
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
RUN=${RUN:-runs/refine_c29}
INIT=${INIT:-campaigns/c29/refine_init.safetensors}
DATA=${DATA:-data/plain_ref}
STEPS=${STEPS:-800}
LR=${LR:-1e-3}
PRESET=${PRESET:-layer_medium}
LOSS=${LOSS:-smape+0.05*relmse_in+0.05*relmse_in_wide}
TAG=${TAG:-}                       # log-name prefix
SEED=${SEED:-}                     # training seed (empty: train's default)
SPP=${SPP:-4 16}                   # random input spp range of training (lo hi)
REPORT=${REPORT:-reports/c29_valscenes}
[ -e "$INIT" ] || $PY scripts/refine_init.py layer-medium "$INIT" --preset "$PRESET"
/usr/bin/time -v $MC train --model refine --preset "$PRESET" --init "$INIT" \
  --data "$DATA" --val-data data/plain_ref --out "$RUN" --steps "$STEPS" --batch 8 --crop 96 --lr "$LR" \
  --loss "$LOSS" --target reference --spp $SPP --val-every 200 --val-images 8 \
  --checkpoint-every 50 --workers 1 --threads 2 ${SEED:+--seed $SEED} --no-progress $( [ -d "$RUN" ] && echo --resume ) > $L/${TAG}train.log 2>&1
$PY scripts/consistency_probe.py "${HELD[@]}" --models layer-medium "$RUN" --spp 4 8 16 --ks 4 > $L/${TAG}probe.log 2>&1
$PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium "$RUN" --spp 4 --summary > $L/${TAG}brightness.log 2>&1
$MC eval --models layer-medium "$RUN" --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out "$REPORT" > $L/${TAG}eval_valscenes.log 2>&1
$PY scripts/compare_on_valscenes.py "$REPORT/results.json" layer-medium "$(basename "$RUN")" --per-scene > $L/${TAG}compare.log 2>&1
echo "${TAG:-leg }done $(date -u +%FT%TZ)" >> $L/${TAG}train.log
