#!/usr/bin/env bash
# Campaign 36, step 3 (campaigns/c36/rules.txt): layer-medium trained with two runs of its network (preset
# medium_2pass: the second run's context reads the samples moved to the first run's output, LayerConfig.passes), from
# campaign 34's start (campaigns/c20/layer_m20d) with campaign 34's leg settings and the three sets on every machine
# (bash campaigns/datasets.sh detail_ref detail_ref2 plain_ref first). A rerun resumes the run.
set -euo pipefail
cd "$(dirname "$0")/../.."
RUN=${RUN:-runs/layer_m36p}
MC=.venv/bin/mcdenoise
# The start: campaign 34's weights with passes 2 (tensors untouched; --init takes the architecture from its file).
INIT=runs/c36/layer_m20d_2pass.safetensors
mkdir -p runs/c36
[ -f $INIT ] || .venv/bin/python scripts/reconfigure_weights.py campaigns/c20/layer_m20d/model.safetensors $INIT \
  --preset medium_2pass --set passes=2
ARGS=(--model layer --preset medium_2pass --init $INIT
      --data data/detail_ref,data/detail_ref2,data/plain_ref --val-data data/detail_ref
      --steps 700 --batch 8 --crop 96 --lr 5e-5 --loss 'smape+0.05*relmse_in+0.05*relmse_in_wide'
      --branch-fraction 0 --amp bf16 --workers 1 --threads 2 --val-every 350 --checkpoint-every 25 --spp 4 16
      --seed 0 --no-progress)
if [ -f "$RUN/config.json" ]; then "$MC" train --out "$RUN" --resume; else "$MC" train --out "$RUN" "${ARGS[@]}"; fi
