#!/usr/bin/env bash
# GPU measurements in one go, each step under its own timeout so that a failing step does
# not cost the rest:
#   1. variants of experiments/jackal.yaml (the shipped agent's recipe), each with three
#      seeds vmapped in one process, all variants at the same time on the one GPU: the
#      learning curves (training-time evaluations from fresh starts on the varied train
#      worlds, per seed) that pick the recipe; every wall-clock is an upper bound of a
#      run alone;
#   2. with the time that is left (BENCH=1): bench update (float32, batch 512, 112x112).
# Results: $OUT/results.tgz (run directories without checkpoints and TensorBoard events)
# and $OUT/gpu_check.log.
#
#   python -m pip install -e '.[cuda]'   # or any jax with CUDA
#   OUT=out/gpu bash scripts/gpu_check.sh
#   OUT=/tmp/gpu_out TINY=1 BENCH=0 bash scripts/gpu_check.sh   # a rehearsal on a CPU
set -u
export MJXVINE_COMPILE_CACHE=0  # compilation counts in the wall-clock
OUT=${OUT:-/tmp/gpu_out}
RES="$OUT/res"
mkdir -p "$RES"
T0=$(date +%s)
log() { echo "[$(date +%H:%M:%S) +$(( $(date +%s) - T0 ))s] $*" | tee -a "$RES/gpu_check.log"; }
python - <<'PY' | tee "$RES/device.txt"
import jax, mujoco; print("jax", jax.__version__, "mujoco", mujoco.__version__, jax.default_backend(),
                          [d.device_kind for d in jax.devices()])
PY
BASE="--config experiments/jackal.yaml --seeds 3"
if [ "${TINY:-0}" = 1 ]; then
  BASE="$BASE --set world.pool_size=2 --set world.train_length_m=4 --set env.num_envs=4
    --set env.max_steps=40 --set sac.batch_size=16 --set sac.buffer_size=2048
    --set sac.warmup_steps=100 --set sac.grad_steps_per_iter=1 --set train.total_env_steps=300
    --set train.eval_every_chunks=2 --set train.eval_starts=2 --set eval.runs_after_train=1
    --set eval.max_steps=40 --set world.test_length_m=10 --set train.iters_per_chunk=5"
  UPDATE="--batch-sizes 16 --grad-steps 2 --set camera.width=41 --set camera.height=41
    --set sac.hidden=32 --set sac.conv_features=8"
  T_TRAIN=${T_TRAIN:-300}; T_BENCH=120; MINUTES=3
else
  BASE="$BASE --set eval.runs_after_train=1 --set train.total_env_steps=${STEPS:-200000}"
  UPDATE="--batch-sizes 512 --grad-steps 8"
  T_TRAIN=${T_TRAIN:-420}; T_BENCH=${T_BENCH:-100}; MINUTES=${MINUTES:-5.5}
fi

train_one() {  # name, extra args
  local name=$1; shift
  local s=$(date +%s)
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.2 timeout $T_TRAIN python -m mjxvine.train $BASE \
    --set train.max_minutes=$MINUTES "$@" --run-dir "$RES/$name" > "$RES/$name.log" 2>&1
  log "$name ($*): exit $? after $(( $(date +%s) - s )) s wall-clock"
  tr '\r' '\n' < "$RES/$name.log" | grep -v "^$" | grep -v "step/s" | tail -12 >> "$RES/gpu_check.log"
}
log "training: python -m mjxvine.train $BASE, four variants"
train_one varied_noise &
train_one varied_noise_conv16 --set sac.conv_features=16 --set sac.auto_alpha=true \
  --set sac.target_entropy=-3.39 &
train_one varied_noise_mirror --set sac.mirror_augment=true &
train_one varied --set env.train_noise_factor=[0,0] &
wait
pack() {
  tar czf "$OUT/results.tgz" -C "$OUT" --exclude "res/*/tb" --exclude "res/*/checkpoints" res
  cp "$RES/gpu_check.log" "$OUT/"
}
pack

if [ "${BENCH:-1}" = 1 ]; then
  log "bench update (float32)"
  timeout $T_BENCH python -m mjxvine.bench update $UPDATE --out "$RES/bench-update.json" 2>&1 \
    | tail -4 | tee -a "$RES/gpu_check.log"
  pack
fi
log "done: $(ls "$OUT")"
