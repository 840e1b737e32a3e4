#!/usr/bin/env bash
# Campaign 36's checks (campaigns/c36/rules.txt): the ensembles E5 (the candidate), E4 and E2s (reported only) against
# the shipped refine-layer_medium_ctx_x2, by the standing replacement rule, on this machine's data. No training.
# Run from the repo root with nothing else running; needs the 46 held-out images, data/test and data/scene_inputs.
set -euo pipefail
cd "$(dirname "$0")/../.."
MC=${MC:-.venv/bin/mcdenoise}; PY=${PY:-.venv/bin/python}; L=campaigns/c36/logs
HELD=(data/detail_ref data/detail_ref2 data/rich_ref3 data/rich_val)
X2=refine-layer_medium_ctx_x2
M=(campaigns/c30/refine_c30a campaigns/c33/refine_c33l campaigns/c33/refine_c33m campaigns/c35/refine_c35s
   campaigns/c35/refine_c35v)
[ -d runs/refine_e5 ] || $PY scripts/refine_ensemble.py runs/refine_e5.safetensors "${M[@]}" \
  --preset layer_medium_ctx_spread --widen --run runs/refine_e5
[ -d runs/refine_e4 ] || $PY scripts/refine_ensemble.py runs/refine_e4.safetensors "${M[0]}" "${M[1]}" "${M[3]}" "${M[4]}" \
  --preset layer_medium_ctx_spread --widen --run runs/refine_e4
[ -d runs/refine_e2s ] || $PY scripts/refine_ensemble.py runs/refine_e2s.safetensors "${M[3]}" "${M[4]}" \
  --preset layer_medium_ctx_spread --run runs/refine_e2s
E=(runs/refine_e5 runs/refine_e4 runs/refine_e2s)
PARTS=${PARTS:-a c b v}  # which parts run (a, c, b as in the rules; v the bias/variance split)
has() { [[ " $PARTS " == *" $1 "* ]]; }
# (a) held-out: paired lines against x2, and the darkening screen against layer-medium.
has a && $PY scripts/consistency_probe.py "${HELD[@]}" --models $X2 "${E[@]}" --spp 4 8 16 --ks 4 > $L/probe.log 2>&1
has a && $PY scripts/brightness_by_quartile.py "${HELD[@]}" --models layer-medium $X2 runs/refine_e5 --spp 4 --summary \
  > $L/brightness.log 2>&1
# (c) procedural test split, torch 1 thread (the block's setting): relMSE and ms/MP in one run.
has c && $MC eval --models $X2 "${E[@]}" --data data/test --threads 1 --spp 4 8 16 --no-classic --oidn high fast \
  --no-progress --no-html --out reports/c36_test > $L/test.log 2>&1
# (b) third-party, seeds 7-12.
has b && $MC eval --models $X2 "${E[@]}" --data data/scene_inputs --spp 4 8 16 --no-classic --oidn high --threads 2 \
  --no-html --no-progress --out reports/c36_valscenes > $L/eval_valscenes.log 2>&1
has b && for e in refine_e5 refine_e4 refine_e2s; do
  $PY scripts/compare_on_valscenes.py reports/c36_valscenes/results.json $X2 $e --per-scene > $L/compare_$e.log 2>&1
done
# The bias/variance split at 4 spp (campaign 35's probe).
has v && $PY scripts/bias_variance_probe.py data/scene_inputs/*spp16_seed* --spp 4 --models $X2 runs/refine_e5 \
  > $L/bias_variance.log 2>&1
echo "checks ($PARTS) done $(date -u +%FT%TZ)" >> $L/checks_done.log
