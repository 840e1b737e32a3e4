#!/usr/bin/env bash
# Campaign 13 on a lent GPU machine (one H100/H200, 16 cores, no network, no Mitsuba installed):
# render fresh per-sample training data with Mitsuba's cuda_ad_rgb variant, then train the runs
# listed in $RUNS (default scripts/gpu_runs_c13.txt: campaign 13's two ~1M-parameter layer models)
# on it side by side, and pack the run folders into $OUT (at most 3 runs: 8 files come back).
#
#   bash scripts/gpu_campaign.sh            # on the GPU machine, from the repository root
#   DEADLINE=555 REF_SPP=512 SEED_D=1601 SEED_R=1602 RUNS=scripts/gpu_runs_c16.txt bash scripts/gpu_campaign.sh
#                                           # campaign 16 (carry .gpu/, with .gpu/layer_m_init.safetensors)
#
# Needs .gpu/site_mi.tar.xz and .gpu/site_dr.tar.xz (made by scripts/gpu_site.sh: the cp312 wheels
# of mitsuba 3.9.1, drjit 1.5.0 and OpenEXR 3.5.3, unpacked and slimmed to the RGB variants so
# that they travel within the device tool's 64 MiB). Everything is time-boxed: DEADLINE seconds
# after the start the run folders are packed, whatever state the training is in (checkpoints
# every 100 steps; the schedule is set from a measured step time so a run normally finishes).
# RESUME_ONLY=1 (campaign 21): a second call on the still-warm machine skips the site, the
# Mitsuba check, the rendering and the calibration leg, and resumes the runs on the shards already
# in $ROOT until the new DEADLINE (the machine keeps /dev/shm only while it stays warm).
# Nothing here is needed to use or test mcdenoise; it is the recipe of campaign 13's weights.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/c13_out}; mkdir -p "$OUT"
DEADLINE=${DEADLINE:-540}   # s from start: runs are packed by then
RENDER_S=${RENDER_S:-150}   # s of rendering (shards are killed then; finished images are kept)
SHARDS=${SHARDS:-12}        # parallel render processes (2/3 detailed world, 1/3 rich)
SPP=${SPP:-12}
REF_SPP=${REF_SPP:-1024}  # reference spp (campaign 16: 512, more scenes in the same seconds)
SEED_D=${SEED_D:-1301}; SEED_R=${SEED_R:-1302}   # dataset seeds of the two worlds (campaign 13's by default)
VARIANT=${VARIANT:-cuda_ad_rgb}; DEVICE=${DEVICE:-cuda}; PY=${PY:-python3}
BATCH=${BATCH:-16}; CROP=${CROP:-128}; CALIB=${CALIB:-40}; WORKERS=${WORKERS:-6}
COUNT_D=${COUNT_D:-240}; COUNT_R=${COUNT_R:-120}   # scenes (x4 views), 25 MB per image at 12 spp
T0=$(date +%s); el() { echo $(( $(date +%s) - T0 )); }
log() { echo "[$(el)s] $*"; }

SITE=/tmp/site; mkdir -p $SITE
if [ -z "${SKIP_SITE:-}" ]; then for f in .gpu/site_*.tar.xz; do tar -C $SITE -xJf "$f" & done; wait; fi
export PYTHONPATH=$SITE:$PWD PYTHONUNBUFFERED=1
export LD_LIBRARY_PATH=/usr/local/nvidia/lib64:/usr/local/nvidia/lib:${LD_LIBRARY_PATH:-}
MC="$PY -m mcdenoise.cli.main"
nvidia-smi -L 2>/dev/null; $PY --version; nproc
(ldconfig -p | grep -iE "nvoptix|rtcore"; ls /usr/local/nvidia/lib64 2>/dev/null | grep -iE "optix|rtcore") | head
# Data and runs in DATA_ROOT, else in RAM when /dev/shm has room (the GPU machine has 128 GB).
ROOT=${DATA_ROOT:-/tmp/c13}
if [ -z "${DATA_ROOT:-}" ]; then
  avail=$(df --output=avail -BG /dev/shm | tail -1 | tr -dc 0-9)
  [ "${avail:-0}" -ge 40 ] && ROOT=/dev/shm/c13
fi
mkdir -p $ROOT/logs; df -h $ROOT | tail -1
log "site unpacked; data in $ROOT"

if [ -z "${RESUME_ONLY:-}" ]; then
$PY - $VARIANT <<'EOF' || { log "Mitsuba $VARIANT does not run here"; exit 3; }
import sys, time, mitsuba as mi
t = time.time(); mi.set_variant(sys.argv[1])
img = mi.render(mi.load_dict(mi.cornell_box()), spp=16)
print("cornell box on", sys.argv[1], img.shape, f"{time.time() - t:.1f} s")
EOF
log "mitsuba ok"

# Render shards, each its own dataset folder (shard i/n of one recipe; their union is the set).
DS="--spp $SPP --ref-spp $REF_SPP --size 128 --variant $VARIANT --max-depth 8 --objects 10-40 --views 4 --split 0.95,0.05,0 --max-gb 60 --no-progress"
ND=$(( SHARDS * 2 / 3 )); NR=$(( SHARDS - ND )); ROOTS=()
for i in $(seq 0 $((ND - 1))); do
  ROOTS+=($ROOT/det_$i)
  timeout -s TERM $RENDER_S $MC dataset --out $ROOT/det_$i --count $COUNT_D --world detailed --seed $SEED_D --shard $i/$ND $DS > $ROOT/logs/render_det_$i.log 2>&1 &
done
for i in $(seq 0 $((NR - 1))); do
  ROOTS+=($ROOT/rich_$i)
  timeout -s TERM $RENDER_S $MC dataset --out $ROOT/rich_$i --count $COUNT_R --world rich --seed $SEED_R --shard $i/$NR $DS > $ROOT/logs/render_rich_$i.log 2>&1 &
done
sleep 45
n=$(ls -d $ROOT/*/proc_* 2>/dev/null | wc -l); log "after 45 s: $n scenes finished"
if [ "$n" -eq 0 ]; then tail -20 $ROOT/logs/render_det_0.log; fi
wait
for r in "${ROOTS[@]}"; do $MC dataset --merge --out $r > /dev/null 2>&1 || log "merge failed: $r"; done
else  # RESUME_ONLY=1: a second call on the warm machine trains on the shards the first call rendered
  ROOTS=($ROOT/det_* $ROOT/rich_*)
fi
GOOD=(); for r in "${ROOTS[@]}"; do [ -s $r/manifest.json ] && GOOD+=($r); done
nimg=$(ls -d $ROOT/*/proc_*/view_* 2>/dev/null | wc -l)
log "rendered: $nimg images in ${#GOOD[@]} shards; $(du -sh $ROOT | cut -f1)"
tail -3 $ROOT/logs/render_det_0.log
[ ${#GOOD[@]} -gt 0 ] || { tar -czf $OUT/logs.tgz -C $ROOT logs; exit 4; }
DATA=$(IFS=,; echo "${GOOD[*]}")

# One line per run in $RUNS: NAME|mcdenoise train arguments (after the common ones, so a flag
# given there wins: argparse keeps the last). All runs train side by side on the one GPU.
RUNS=${RUNS:-scripts/gpu_runs_c13.txt}
NAMES=(); ARGS=()
while IFS='|' read -r name rest; do
  [[ -z "$name" || "$name" == \#* ]] && continue
  NAMES+=("$name"); ARGS+=("$rest")
done < "$RUNS"
log "runs: ${NAMES[*]} (from $RUNS)"
COMMON="--data $DATA --val-data ${GOOD[0]} --batch $BATCH --crop $CROP --loss tonemapped_l2 --lr 1e-3 --workers $WORKERS --threads 2 --val-every 0 --val-images 8 --checkpoint-every 100 --keep-every 100000 --spp 2 $SPP --amp bf16 --device $DEVICE --no-progress"
R=$ROOT/runs; mkdir -p $R
train_all() {  # $1 = steps per run (space-separated, one per run), $2 = timeout s (0: none), rest: extra args
  local steps=($1) limit=$2; shift 2
  for k in "${!NAMES[@]}"; do
    eval "local extra=(${ARGS[$k]})"
    if [ "$limit" -gt 0 ]; then
      timeout -s TERM $limit $MC train --out $R/${NAMES[$k]} --steps ${steps[$k]} $COMMON "${extra[@]}" "$@" >> $ROOT/logs/train_${NAMES[$k]}.log 2>&1 &
    else
      $MC train --out $R/${NAMES[$k]} --steps ${steps[$k]} $COMMON "${extra[@]}" "$@" >> $ROOT/logs/train_${NAMES[$k]}.log 2>&1 &
    fi
  done
  wait
}
(nvidia-smi --query-gpu=name,utilization.gpu,memory.used --format=csv -l 20 > $ROOT/logs/gpu.txt 2>&1 &)
if [ -z "${RESUME_ONLY:-}" ]; then
  train_all "$(for n in "${NAMES[@]}"; do echo -n "$CALIB "; done)" 0
  for n in "${NAMES[@]}"; do tail -n 2 $ROOT/logs/train_$n.log; done
fi
steps_for() {  # run folder -> total steps that fit before the deadline, from the run's last step
  $PY - "$1" $CALIB "$(( DEADLINE - $(el) - 45 ))" <<'EOF'
import csv, statistics, sys
rows = [r for r in csv.DictReader(open(sys.argv[1] + "/metrics.csv")) if r["s_per_step"] and int(r["step"]) > min(10, int(sys.argv[2]) // 2)]
s = statistics.median(float(r["s_per_step"]) for r in rows)
c = int(rows[-1]["step"])  # the calibration leg's end, or where the last call stopped
print(max(c + 1, c + int(max(0, int(sys.argv[3])) / (s * 1.25))), file=sys.stdout)
print(f"{sys.argv[1]}: {s:.3f} s/step", file=sys.stderr)
EOF
}
STEPS=""; for n in "${NAMES[@]}"; do STEPS="$STEPS $(steps_for $R/$n)"; done
log "resuming ${NAMES[*]} to$STEPS steps"
train_all "$STEPS" $(( DEADLINE - $(el) - 15 )) --resume
log "training done"
for n in "${NAMES[@]}"; do tail -n 3 $ROOT/logs/train_$n.log; done
for r in "${GOOD[@]}"; do mkdir -p $ROOT/logs/ds/$(basename $r); cp $r/dataset.json $r/manifest.json $ROOT/logs/ds/$(basename $r)/; done
tar -czf $OUT/logs.tgz -C $ROOT logs
# Two files per run (each must stay under the device tool's 16 MB and 8 files in all): the run
# without its checkpoints, and its newest checkpoint (a killed run's weights are there).
for m in "${NAMES[@]}"; do
  tar -czf $OUT/$m.tgz -C $R --exclude=checkpoints $m
  ck=$(ls -d $R/$m/checkpoints/step_* 2>/dev/null | tail -n 1)
  [ -n "$ck" ] && tar -czf $OUT/${m}_ckpt.tgz -C $R $m/checkpoints/$(basename $ck)
done
ls -la $OUT; log "packed"
