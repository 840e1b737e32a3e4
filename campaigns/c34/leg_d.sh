#!/usr/bin/env bash
# Campaign 34, step 2 (campaigns/c34/rules.txt): layer-medium fine-tuned from the shipped weights with the wide-lens
# set data/dof_ref added (bash campaigns/datasets.sh dof_ref first), campaign 27's leg settings otherwise; then its
# 0.25 average with the shipped weights. A rerun resumes the run. Step 4 is the same with SET and LEG changed
# (campaigns/c34/leg_s.sh).
set -euo pipefail
cd "$(dirname "$0")/../.."
LEG=${LEG:-d} SET=${SET:-data/dof_ref}
RUN=runs/layer_m34$LEG
MC=.venv/bin/mcdenoise
ARGS=(--model layer --preset medium --init campaigns/c20/layer_m20d/model.safetensors
      --data data/detail_ref,data/detail_ref2,data/plain_ref,$SET --val-data data/detail_ref
      --steps 700 --batch 8 --crop 96 --lr 5e-5 --loss 'smape+0.05*relmse_in+0.05*relmse_in_wide'
      --branch-fraction 0 --amp bf16 --workers 1 --threads 2 --val-every 350 --checkpoint-every 50 --spp 4 16
      --seed 0 --no-progress)
if [ -f "$RUN/config.json" ]; then "$MC" train --out "$RUN" --resume; else "$MC" train --out "$RUN" "${ARGS[@]}"; fi
mkdir -p runs/c34
.venv/bin/python scripts/average_weights.py runs/c34/avg_m34${LEG}_25.safetensors campaigns/c20/layer_m20d "$RUN" --weights 0.75 0.25
