#!/usr/bin/env bash
# Campaign 32's leg J (campaigns/c32/rules.txt), report only: campaign 31's leg F (the shipped
# refine-layer_medium_ctx) trained again with --seed 1, then the checks of campaigns/c32/checks.sh.
# Leg K: SEED=2 LEG=k bash campaigns/c32/leg_j.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c32/logs
SEED=${SEED:-1} LEG=${LEG:-j}
RUN=runs/refine_c32$LEG INIT=campaigns/c30/refine_ctx_init.safetensors
[ -e "$INIT" ] || $PY scripts/refine_init.py layer-medium "$INIT" --preset layer_medium_ctx
/usr/bin/time -v $MC train --model refine --preset layer_medium_ctx \
  --init "$INIT" --data data/plain_ref,data/detail_ref,data/detail_ref2 --val-data data/plain_ref --out "$RUN" \
  --steps 800 --batch 8 --crop 96 --lr 1e-3 --loss "smape+0.05*relmse_in+0.05*relmse_in_wide+512*tonemapped_l2" \
  --target reference --spp 4 16 --val-every 200 --val-images 8 --checkpoint-every 50 --workers 1 --threads 2 --seed $SEED \
  --no-progress $( [ -d "$RUN" ] && echo --resume ) > $L/${LEG}_train.log 2>&1
bash campaigns/c32/checks.sh "$RUN" $LEG
echo "leg $LEG done $(date -u +%FT%TZ)" >> $L/${LEG}_train.log
