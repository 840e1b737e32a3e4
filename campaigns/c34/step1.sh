#!/usr/bin/env bash
# Campaign 34, step 1 (campaigns/c34/rules.txt): the shipped models and OIDN 2.5.1 high on the wide-lens held-out
# images (data/dof_ref's val split), and the geometric-mean ratio to OIDN high beside the standing held-out set's.
# Step 3: VAL=data/studio_ref TAG=step3 bash campaigns/c34/step1.sh
set -euo pipefail
cd "$(dirname "$0")/../.."
L=campaigns/c34/logs VAL=${VAL:-data/dof_ref} TAG=${TAG:-step1}
OUT=reports/c34_$(basename "$VAL")_val
.venv/bin/mcdenoise eval --models layer-medium kpcn-pixel refine-layer_medium_ctx_x2 --data $VAL --split val \
  --spp 4 8 16 --no-classic --oidn high --threads 1 --no-html --no-progress --out $OUT | tee $L/${TAG}_eval.log
.venv/bin/python scripts/ratio_by_lighting.py $OUT/results.json oidn-high layer-medium kpcn-pixel \
  refine-layer_medium_ctx_x2 --all | tee $L/${TAG}_ratio.log
.venv/bin/python scripts/ratio_by_lighting.py $OUT/results.json oidn-high layer-medium --all --metric psnr \
  | tee $L/${TAG}_psnr.log
# The standing held-out set (46 images) and the third-party renderings, for comparison.
for R in reports/c32_heldout_bands reports/valscenes_seeds; do
  .venv/bin/python scripts/ratio_by_lighting.py $R/results.json oidn-high layer-medium --all
  .venv/bin/python scripts/ratio_by_lighting.py $R/results.json oidn-high layer-medium --all --by-noise
  .venv/bin/python scripts/ratio_by_lighting.py $R/results.json oidn-high layer-medium --all --metric psnr
done | tee $L/${TAG}_reference_ratios.log
