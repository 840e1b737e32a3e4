#!/usr/bin/env bash
# studio_plain's val split (20 images): a candidate beside leg A (campaign 30), x2 and OIDN 2.5.1 high at 4 / 8 / 16 spp,
# and the geometric mean of per-image relMSE ratios to leg A and to OIDN high. Usage: studio_val.sh CANDIDATE TAG
set -euo pipefail
cd "$(dirname "$0")/../.."
CAND=$1; TAG=$2; L=campaigns/c35/logs; OUT=reports/c35${TAG%_}_studio_val
.venv/bin/mcdenoise eval --models campaigns/c30/refine_c30a refine-layer_medium_ctx_x2 "$CAND" --data data/studio_plain \
  --split val --spp 4 8 16 --no-classic --oidn high --threads 2 --no-html --no-progress --out $OUT > $L/${TAG}studio_val.log 2>&1
.venv/bin/python scripts/ratio_by_lighting.py $OUT/results.json refine_c30a "$(basename "${CAND%.safetensors}")" --all \
  > $L/${TAG}studio_val_ratio.log 2>&1
.venv/bin/python scripts/ratio_by_lighting.py $OUT/results.json oidn-high refine_c30a refine-layer_medium_ctx_x2 \
  "$(basename "${CAND%.safetensors}")" --all >> $L/${TAG}studio_val_ratio.log 2>&1
