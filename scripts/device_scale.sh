#!/usr/bin/env bash
# The data-at-scale run of docs/neural.md ("Ten times the data"), as it ran on one lent GPU
# machine (16 cores, one OpenCL GPU) in a single call with a hard time limit: several
# `clvol dataset make --serial --part I/N` processes share the GPU (the host work of a shard,
# volume generation and its bookkeeping, runs on the CPU cores beside it), each stopped at the
# time budget (a shard is written whole or not at all, so a stopped data set is a valid subset
# of its spec and a rerun resumes it); then the final model and the leave-one-family-out runs
# train on torch's device. On a CPU machine the same data commands run on Ray instead
# (`clvol dataset make DIR ... --augment 0.5`, no --part), only slower.
#
# A record of the run of 2026-11-27, not a recipe to repeat as is: it made 26 shards in 220 s,
# because 16 processes time-slice one GPU and each builds the path tracer's program (~60 s).
# On one GPU make the training sets with one process and large shards (docs/dataset.md,
# "On a GPU"): one `clvol dataset make` per data set, without --part.
#
#   DATA_S=270 TRAIN_S=150 NPROC=14 DEVICE=cuda scripts/device_scale.sh RUNS_DIR
# Environment: DATA_S, TRAIN_S (seconds), NPROC (dataset processes), DEVICE (torch), SMALL=1
# (a dry run at toy sizes).
set -uo pipefail
R=${1:?usage: scripts/device_scale.sh RUNS_DIR}
mkdir -p "$R"
HERE=$(cd "$(dirname "$0")/.." && pwd)
DATA_S=${DATA_S:-270}; TRAIN_S=${TRAIN_S:-150}; NPROC=${NPROC:-14}; DEVICE=${DEVICE:-cuda}
if [ "${SMALL:-0}" = 1 ]; then
  V=24; PTS=32; PATHS=32; HOV=6; OOFV=4; BASE=64; STEPS=60; LSTEPS=30; BATCH=64; RES=32,48
else
  V=4000; PTS=1024; PATHS=128; HOV=40; OOFV=48; BASE=64; STEPS=8000; LSTEPS=2000; BATCH=1024; RES=32,128
fi
common="--serial --no-progress --base $BASE --albedo 0.3,1.0 --per-order-labels --resolution $RES"
# in-family training data: clouds (the benchmark's), and the whole domain; half the volumes
# with randomised density structure (docs/neural.md, "A training distribution that generalizes")
cloud="--seed 41 --volumes $V --heldout 0 --configs 4 --points $PTS --paths $PATHS --optical-thickness 2,200 --families cumulus,flat_cumulus,stratus,plume,noise --augment 0.5"
all="--seed 42 --volumes $V --heldout 0 --configs 4 --points $PTS --paths $PATHS --optical-thickness 1,1000 --augment 0.5"
# evaluation sets: unseen volumes of the training families, and the out-of-family clouds
ho="--seed 43 --volumes $((HOV + 1)) --heldout $HOV --configs 4 --points 128 --paths 256 --optical-thickness 2,200"
oof="--seed 44 --volumes $OOFV --heldout 0 --configs 4 --points 128 --paths 256 --optical-thickness 2,200 --families nubis,sphere_cumulus"
n_ho=$(( NPROC / 8 + 1 )); n_oof=$(( NPROC / 6 + 1 )); n_all=$(( (NPROC - n_ho - n_oof) * 4 / 10 ))
n_cloud=$(( NPROC - n_ho - n_oof - n_all )); [ $n_cloud -lt 1 ] && n_cloud=1; [ $n_all -lt 1 ] && n_all=1
pids=()
launch() {   # name, parts, options
  local name=$1 n=$2; shift 2
  for ((i = 0; i < n; i++)); do
    timeout -s INT -k 30 "$DATA_S" ${PYTHON:-python} -m clvol dataset make "$R/$name" $common "$@" --part $i/$n \
      > "$R/log_${name}_$i.txt" 2>&1 &
    pids+=($!)
  done
}
t0=$(date +%s)
launch gx_cloud $n_cloud $cloud
launch gx_all $n_all $all
launch gx_ho $n_ho $ho
launch gx_oof $n_oof $oof
wait "${pids[@]}"
echo "data: $(( $(date +%s) - t0 )) s"
for d in gx_cloud gx_all gx_ho gx_oof; do
  echo "$d: $(ls "$R/$d" | grep -c '^shard_') shards"
done
# comma list of the folders that hold shards (a time-boxed set may have none yet)
have() { local out=""; for d in "$@"; do
  ls "$R/$d" 2>/dev/null | grep -q '^shard_' && out="$out${out:+,}$R/$d"; done; echo "$out"; }
TRAIN_SETS=$(have gx_cloud gx_all gx_ho); ALL_SETS=$(have gx_cloud gx_all gx_ho gx_oof)
EVAL_SETS=$(have gx_ho gx_oof)
# the final model: fine-tuned from the shipped one on everything in family
PY=${PYTHON:-python}
train="$PY $HERE/scripts/train.py"
opts="--albedo-draws 4 --albedo-input log1m --floor inf --device $DEVICE --eval-every 2000 --checkpoint-every 1000"
lopts="--albedo-draws 4 --albedo-input log1m --floor inf --device cpu --threads 1 --eval-every 1000000 --checkpoint-every 1000"
timeout -s INT -k 60 "$TRAIN_S" $train "$TRAIN_SETS" "$R/final" --steps $STEPS --batch $BATCH \
  --time-budget $(( TRAIN_S - 30 )) \
  --lr 5e-4 --init "$HERE/clvol/data/weights/full_albedo.npz" $opts --export "$R/final/w.npz" \
  > "$R/log_final.txt" 2>&1 &
fpid=$!
# leave-one-family-out at small scale (from scratch: the shipped weights saw every family),
# on the CPU cores (one thread each) while the final model has the GPU
lofo=(none cumulus flat_cumulus stratus plume noise sphere blob torus box union)
for F in "${lofo[@]}"; do
  ex=""; [ "$F" != none ] && ex="--exclude-families $F"
  ( timeout -s INT -k 60 "$TRAIN_S" $train "$ALL_SETS" "$R/lofo_$F" --steps $LSTEPS \
      --time-budget $(( TRAIN_S - 60 )) \
      --batch 256 --train-fraction 0.25 $lopts $ex --export "$R/lofo_$F/w.npz" > "$R/log_lofo_$F.txt" 2>&1
    [ -f "$R/lofo_$F/w.npz" ] && $train "$ALL_SETS" "$R/lofo_$F" $ex --evaluate "$R/lofo_$F/w.npz" \
      --threads 1 --device $DEVICE > "$R/eval_lofo_$F.txt" 2>&1 ) &
done
wait $fpid
echo "final: rc $?"
if [ -f "$R/final/w.npz" ]; then
  $train "$EVAL_SETS" "$R/final" --evaluate "$R/final/w.npz" --device $DEVICE > "$R/eval_final.txt" 2>&1
  $train "$EVAL_SETS" "$R/shipped" --evaluate "$HERE/clvol/data/weights/full_albedo.npz" \
    --device $DEVICE > "$R/eval_shipped.txt" 2>&1
fi
wait
echo "all: $(( $(date +%s) - t0 )) s"
