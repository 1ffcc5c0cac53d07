#!/usr/bin/env bash
# Every GPU measurement of the open issues in ONE device call, each step under its own
# timeout so that a failing step does not cost the rest:
#   1. the headline run (experiments/headline.yaml: train, evaluate on the test world) and
#      the export of its best policy;
#   2. with the time that is left (BENCH=1): bench update and bench env.
# Results land in $OUT: one tarball (res/) plus the small summaries (the device tool
# brings back at most 8 files).
#
#   here, once:        ../shared/device/wheels.sh
#   device call:       carry [".whl"], command:
#                      source .whl/setup.sh && bash scripts/gpu_check.sh
#   CPU rehearsal:     OUT=/tmp/gpu_out TINY=1 bash scripts/gpu_check.sh
#
# TINY=1 shrinks every step to seconds (small images, few envs, short episodes), to test
# this script on a CPU before spending device time.
set -u
export MJXVINE_COMPILE_CACHE=0  # a fresh machine: compilation counts in the wall-clock
OUT=${OUT:-/tmp/gpu_out}
RES="$OUT/res"
mkdir -p "$RES"
T0=$(date +%s)
log() { echo "[$(date +%H:%M:%S) +$(( $(date +%s) - T0 ))s] $*" | tee -a "$RES/gpu_check.log"; }
python - <<'PY' | tee "$RES/device.txt"
import jax, mujoco; print("jax", jax.__version__, "mujoco", mujoco.__version__, jax.default_backend(),
                          [d.device_kind for d in jax.devices()])
PY
if [ "${TINY:-0}" = 1 ]; then
  SMALL="--set camera.width=40 --set camera.height=40 --set sac.hidden=32 --set sac.conv_features=8"
  HEADLINE="--config experiments/headline.yaml $SMALL --set world.pool_size=2 --set world.train_length_m=4
    --set env.num_envs=4 --set env.max_steps=60 --set sac.batch_size=32 --set sac.buffer_size=4096
    --set sac.warmup_steps=200 --set sac.grad_steps_per_iter=2 --set train.total_env_steps=600
    --set train.eval_every_chunks=5 --set train.eval_starts=2 --set eval.runs_after_train=1
    --set eval.max_steps=60 --set world.test_length_m=10"
  UPDATE="--batch-sizes 32 --grad-steps 2 $SMALL"
  ENV="--sizes 4,16 --steps 2 $SMALL"
  T_TRAIN=600; T_BENCH=300
else
  HEADLINE="--config experiments/headline.yaml"
  UPDATE="--batch-sizes 512 --grad-steps 8"
  ENV="--sizes 1024,4096,16384 --steps 10"
  T_TRAIN=${T_TRAIN:-530}; T_BENCH=${T_BENCH:-150}
fi

# The headline and the same config with mirror augmentation (sac.mirror_augment: on the
# CPU it centred the agent but lost curved test lanes, one seed), trained at the same
# time on the one GPU (each process gets 40 % of its memory), so that one device call
# gives both: each wall-clock is an upper bound of the run alone.
train_one() {  # name, extra args
  local name=$1; shift
  local s=$(date +%s)
  XLA_PYTHON_CLIENT_MEM_FRACTION=0.4 timeout $T_TRAIN python -m mjxvine.train $HEADLINE "$@" \
    --run-dir "$RES/$name" > "$RES/$name.log" 2>&1
  local rc=$?
  echo "$(( $(date +%s) - s ))" > "$RES/${name}_wall_s.txt"
  log "$name: exit $rc after $(( $(date +%s) - s )) s wall-clock (compilation and evaluation included)"
  tr '\r' '\n' < "$RES/$name.log" | grep -v "^$" | grep -v "step/s" | tail -40 >> "$RES/gpu_check.log"
  timeout 90 python -m mjxvine.export --checkpoint "$RES/$name" --out "$RES/$name.npz" 2>&1 \
    | tee -a "$RES/gpu_check.log"
}
log "training: python -m mjxvine.train $HEADLINE [--set sac.mirror_augment=true]"
train_one headline &
train_one headline_mirror --set sac.mirror_augment=true &
wait
cp "$RES/headline.npz" "$OUT/jackal.npz" 2>/dev/null
cp "$RES/headline/eval/results.md" "$OUT/" 2>/dev/null
cp "$RES/headline_mirror/eval/results.md" "$OUT/results_mirror.md" 2>/dev/null
pack() {
  tar czf "$OUT/results.tgz" -C "$OUT" --exclude "res/*/tb" \
    --exclude "res/*/checkpoints" res
  cp "$RES/gpu_check.log" "$OUT/"
}
pack

if [ "${BENCH:-1}" = 1 ]; then
  for dt in float32 bfloat16; do
    log "bench update ($dt)"
    timeout $T_BENCH python -m mjxvine.bench update $UPDATE --set sac.compute_dtype=$dt \
      --out "$RES/bench-update-$dt.json" 2>&1 | tail -4 | tee -a "$RES/gpu_check.log"
    pack
  done
  log "bench env"
  timeout $T_BENCH python -m mjxvine.bench env $ENV --out "$RES/bench-env.json" 2>&1 \
    | tail -6 | tee -a "$RES/gpu_check.log"
  pack
fi
log "done: $(ls "$OUT")"
