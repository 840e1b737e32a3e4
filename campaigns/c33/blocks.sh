#!/bin/bash
# Campaign 33 (campaigns/c33/rules.txt, step 3): the three RESULTS.md blocks with refine-layer_medium_ctx_x2 added,
# by campaign 32's script. Run from the repo root, nothing else running (the ms/MP columns).
M="kpcn kpcn-pixel sbmc layer layer-medium refine-layer_medium_ctx refine-layer_medium_ctx_x2 wskp combine-ens combine-ens_kpcn combine-kpcn combine-own" \
  exec bash "$(dirname "$0")/../c32/blocks.sh"
