#!/usr/bin/env bash
# Campaign 34, step 4 (campaigns/c34/rules.txt): step 2's leg with the studio set without small emitters,
# data/studio_plain, in place of data/dof_ref (bash campaigns/datasets.sh studio_plain first): runs/layer_m34s.
set -euo pipefail
LEG=s SET=data/studio_plain exec bash "$(dirname "$0")/leg_d.sh"
