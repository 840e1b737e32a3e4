#!/bin/bash
# Committed copy of the script that ran as logs/c32_blocks.sh (campaign 32, step 1). Run from the repo root.
# Regenerate the three RESULTS.md blocks with refine-layer_medium_ctx (c31 leg F) shipped; M="..." names other models (campaign 33).
set -x
M=${M:-"kpcn kpcn-pixel sbmc layer layer-medium refine-layer_medium_ctx wskp combine-ens combine-ens_kpcn combine-kpcn combine-own"}
date
time .venv/bin/mcdenoise eval --models $M --data data/test --threads 1 --spp 4 8 16 --out reports/test --no-classic --oidn high fast high-pf --no-progress --results-md docs/RESULTS.md --section procedural-test
date
time .venv/bin/mcdenoise eval --models $M --scenes ../shared/valscenes --spp 4 8 16 --out reports/valscenes --no-classic --oidn high fast high-pf --no-progress --results-md docs/RESULTS.md --section valscenes
date
time .venv/bin/mcdenoise eval --models $M --scenes ../shared/valscenes --render-seed 7 8 9 10 11 12 --spp 4 8 16 --out reports/valscenes_seeds --no-classic --oidn high fast high-pf --no-progress --results-md docs/RESULTS.md --section valscenes_seeds
date
