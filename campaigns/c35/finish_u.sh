#!/usr/bin/env bash
# Finish campaign 35's step 5 (campaigns/c35/rules.txt): S35 on studio_plain's val split (the ratio U35 / S35 there is
# U35's ratio to leg A over S35's, the same 20 images), then leg U35, resumed from its latest checkpoint, and its checks.
# On a new machine first: cp -r campaigns/c35/refine_c35s campaigns/c35/refine_c35u runs/
set -euo pipefail
cd "$(dirname "$0")/../.."
[ -s campaigns/c35/logs/s_studio_val_ratio.log ] || bash campaigns/c35/studio_val.sh runs/refine_c35s s_
exec bash campaigns/c35/leg_u.sh
