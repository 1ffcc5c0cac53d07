#!/usr/bin/env bash
# GPU measurements in one go, each step under its own timeout so that a failing step does
# not cost the rest:
#   1. experiments/jackal.yaml (the shipped agent's recipe) from seeds 0, 1 and 2,
#      vmapped in one process, for STEPS env steps (default 80,000; the recipe trains
#      70,000) with the backend's own tower; each member chooses its own checkpoint
#      of its 4 best evaluations on the recipe's validation worlds (train.select_worlds:
#      RUN/selected_members/member<k>.npz), never on a test world;
#   2. the paper's suite (`evaluate --suite paper`) of each member's chosen actor, the
#      three at once.
# Results: $OUT/results.tgz (the run directory without checkpoints and TensorBoard
# events, the suites' reports) and $OUT/gpu_check.log.
#
#   python -m pip install -e '.[cuda]'   # or any jax with CUDA
#   OUT=out/gpu bash scripts/gpu_check.sh
#   OUT=/tmp/gpu_out TINY=1 bash scripts/gpu_check.sh   # a rehearsal on a CPU
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
TRAIN="--config experiments/jackal.yaml --num-seeds 3 --set eval.runs_after_train=0"
MEMBERS="0 1 2"
if [ "${TINY:-0}" = 1 ]; then
  TRAIN="$TRAIN --set world.pool_size=2 --set world.train_length_m=4 --set env.num_envs=4
    --set env.max_steps=40 --set sac.batch_size=16 --set sac.buffer_size=2048
    --set sac.warmup_steps=100 --set sac.grad_steps_per_iter=1 --set train.total_env_steps=300
    --set train.eval_every_chunks=2 --set train.eval_starts=2 --set eval.max_steps=40
    --set world.test_length_m=10 --set train.iters_per_chunk=5 --set train.select_worlds=1
    --set train.select_candidates=2"
  MEMBERS="0"; T_TRAIN=900; T_EVAL=600
else
  # 4 candidates per member, as the recipe: the choice within the step's timeout
  TRAIN="$TRAIN --set train.total_env_steps=${STEPS:-80000} --set train.select_candidates=4"
  # a run stopped by the timeout checkpoints (SIGTERM) but makes no choice: the suite
  # then drives each member's best fresh-start checkpoint
  T_TRAIN=${T_TRAIN:-540}; T_EVAL=${T_EVAL:-180}
fi
pack() {
  tar czf "$OUT/results.tgz" -C "$OUT" --exclude "res/*/tb" --exclude "res/*/checkpoints" res
  cp "$RES/gpu_check.log" "$OUT/"
}

RUN="$RES/jackal-seeds"
log "training: python -m mjxvine.train $TRAIN"
s=$(date +%s)
XLA_PYTHON_CLIENT_MEM_FRACTION=0.5 timeout $T_TRAIN python -m mjxvine.train $TRAIN \
  --out "$RUN" > "$RES/train.log" 2>&1
log "training: exit $? after $(( $(date +%s) - s )) s wall-clock"
tr '\r' '\n' < "$RES/train.log" | grep -v "^$" | grep -v "step/s" | tail -12 >> "$RES/gpu_check.log"
cat "$RUN/best_members/scores.json" >> "$RES/gpu_check.log" 2>/dev/null
for k in $MEMBERS; do
  python -c "import json, sys; r = json.load(open(sys.argv[1])); print('member', sys.argv[2],
    'chose', r['selected'], 'env steps of', [c['env_steps'] for c in r['candidates']])" \
    "$RUN/selected_members/selection$k.json" "$k" >> "$RES/gpu_check.log" 2>&1
done
pack

log "the paper's suite of each member's chosen actor"
for k in $MEMBERS; do
  ( s=$(date +%s)
    policy="$RUN/selected_members/member$k.npz"
    [ -f "$policy" ] || policy="$RUN/best_members/member$k.npz"  # no choice made: its best
    XLA_PYTHON_CLIENT_MEM_FRACTION=0.25 timeout $T_EVAL python -m mjxvine.evaluate \
      --policy "$policy" --suite paper --out "$RES/suite-member$k" \
      > "$RES/suite-member$k.log" 2>&1
    log "suite of member $k: exit $? after $(( $(date +%s) - s )) s" ) &
done
wait
for k in $MEMBERS; do
  sed -n 1,30p "$RES/suite-member$k/report.md" >> "$RES/gpu_check.log" 2>/dev/null
done
pack
log "done: $(ls "$OUT")"
