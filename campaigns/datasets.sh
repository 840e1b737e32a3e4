#!/usr/bin/env bash
# The datasets of the layer-medium campaigns (21-28), by name, with the recipes of docs/TRAINING.md.
# Each comes back with the same scenes, splits and manifest on any machine (--variant llvm_ad_rgb);
# a rerun resumes. Usage:
#   bash campaigns/datasets.sh heldout         # the 46 held-out val images only (--only-split val)
#   bash campaigns/datasets.sh train           # every set of the latest leg, in full (hours on 2 cores)
#   bash campaigns/datasets.sh detail_ref ...  # named sets, in full
set -euo pipefail
cd "$(dirname "$0")/.."
MC=${MC:-.venv/bin/mcdenoise}
COMMON=(--spp 16 --ref-spp 256 --size 128 --variant llvm_ad_rgb --max-depth 8 --objects 10-40 --no-progress)
DETAIL=(--generator 4 --views 2 --world detailed --split 0.9,0.1,0)
RICH=(--generator 2 --views 2 --world rich --split 0.9,0.1,0)
PLAIN=(--generator 4 --views 2 --world detailed --small-emitters 0 --split 0.75,0.25,0)

recipe() {  # NAME [extra options]: render one set
  local name=$1; shift
  case $name in
    detail_ref)  "$MC" dataset --out data/detail_ref  --count 72 --seed 196 "${COMMON[@]}" "${DETAIL[@]}" "$@" ;;
    detail_ref2) "$MC" dataset --out data/detail_ref2 --count 72 --seed 197 "${COMMON[@]}" "${DETAIL[@]}" "$@" ;;
    detail_ref3) "$MC" dataset --out data/detail_ref3 --count 72 --seed 198 "${COMMON[@]}" "${DETAIL[@]}" "$@" ;;
    rich_ref3)   "$MC" dataset --out data/rich_ref3   --count 48 --seed 194 "${COMMON[@]}" "${RICH[@]}" "$@" ;;
    plain_ref)   "$MC" dataset --out data/plain_ref   --count 48 --seed 2602 "${COMMON[@]}" "${PLAIN[@]}" "$@" ;;
    plain_ref2)  "$MC" dataset --out data/plain_ref2  --count 64 --seed 2701 "${COMMON[@]}" "${PLAIN[@]}" "$@" ;;
    # dof_ref (campaign 34): every scene through a wide lens; a fifth of the scenes held out.
    dof_ref)     "$MC" dataset --out data/dof_ref     --count 48 --seed 3401 "${COMMON[@]}" --generator 4 --views 2 \
                   --world detailed --strong-dof 1 --split 0.8,0.2,0 "$@" ;;
    # studio_ref (campaign 34): a few objects on the ground under an environment, as product shots.
    studio_ref)  "$MC" dataset --out data/studio_ref  --count 48 --seed 3501 "${COMMON[@]/10-40/2-6}" --generator 4 --views 2 \
                   --world detailed --kind outdoor --split 0.8,0.2,0 "$@" ;;
    # studio_plain (campaign 34): studio_ref without the small emitters, as product shots.
    studio_plain) "$MC" dataset --out data/studio_plain --count 48 --seed 3502 "${COMMON[@]/10-40/2-6}" --generator 4 --views 2 \
                   --world detailed --kind outdoor --small-emitters 0 --split 0.8,0.2,0 "$@" ;;
    # rich_val: all val, one view, reference at 512 spp, no variant recorded (made before the field).
    rich_val)    "$MC" dataset --out data/rich_val --generator 2 --count 8 --views 1 --spp 16 --ref-spp 512 --size 128 \
                   --world rich --seed 191 --max-depth 8 --objects 10-40 --split 0,1,0 --no-progress "$@" ;;
    *) echo "campaigns/datasets.sh: unknown set '$name'" >&2; exit 2 ;;
  esac
}

[ $# -ge 1 ] || { sed -n 4,7p "$0" >&2; exit 2; }
for arg in "$@"; do
  case $arg in
    heldout) for s in detail_ref detail_ref2 rich_ref3; do recipe "$s" --only-split val; done; recipe rich_val ;;
    train)   for s in detail_ref detail_ref2 detail_ref3 rich_ref3 plain_ref plain_ref2; do recipe "$s"; done ;;
    *)       recipe "$arg" ;;
  esac
done
