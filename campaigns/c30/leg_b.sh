#!/usr/bin/env bash
# Campaign 30's leg B (campaigns/c30/rules.txt): leg A failed the held-out rule, so leg B asks what the loss
# alone does: leg A without the context features (preset layer_medium), everything else unchanged.
set -euo pipefail
cd "$(dirname "$0")/../.."
RUN=runs/refine_c30b INIT=campaigns/c30/refine_init.safetensors PRESET=layer_medium TAG=b_ \
  REPORT=reports/c30b_valscenes exec bash campaigns/c30/leg_a.sh
