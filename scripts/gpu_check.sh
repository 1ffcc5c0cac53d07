#!/usr/bin/env bash
# Every GPU measurement of the open issues (speed: bench update/env; the headline run) in
# ONE device call, each step under its own timeout so that a failing step does not cost
# the rest. Results land in $OUT (device tool: at most 8 files come back), as one tarball
# plus the small summaries.
#
#   here, once:        ../shared/device/wheels.sh
#   device call:       carry [".whl"], command:
#                      source .whl/setup.sh && bash scripts/gpu_check.sh
#   CPU rehearsal:     OUT=/tmp/gpu_out TINY=1 bash scripts/gpu_check.sh
#
# TINY=1 shrinks every step to seconds (small images, few envs), to test this script on a
# CPU before spending device time.
set -u
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT/res"
RES="$OUT/res"
log() { echo "[$(date +%H:%M:%S)] $*" | tee -a "$RES/gpu_check.log"; }
python - <<'PY' | tee "$RES/device.txt"
import jax; print(jax.__version__, jax.default_backend(), [d.device_kind for d in jax.devices()])
PY
if [ "${TINY:-0}" = 1 ]; then
  SMALL="--set camera.width=40 --set camera.height=40 --set sac.hidden=32 --set sac.conv_features=8"
  UPDATE="--batch-sizes 32 --grad-steps 2 $SMALL"
  ENV="--sizes 4,16 --steps 2 $SMALL"
  HEADLINE="--config experiments/smoke.yaml --set train.total_env_steps=400 --set train.eval_every_chunks=4 --set train.eval_starts=2 --set eval.runs_after_train=1"
  T_BENCH=300; T_TRAIN=600
else
  UPDATE="--batch-sizes 512 --grad-steps 8"
  ENV="--sizes 1024,4096,16384 --steps 10"
  HEADLINE="--config experiments/fast.yaml --set train.max_minutes=${HEADLINE_MINUTES:-4}"
  T_BENCH=150; T_TRAIN=420
fi
log "bench update float32"
timeout $T_BENCH python -m mjxvine.bench update $UPDATE --out "$RES/bench-update-f32.json" 2>&1 | tail -5 | tee -a "$RES/gpu_check.log"
log "bench update bfloat16"
timeout $T_BENCH python -m mjxvine.bench update $UPDATE --set sac.compute_dtype=bfloat16 --out "$RES/bench-update-bf16.json" 2>&1 | tail -5 | tee -a "$RES/gpu_check.log"
log "bench env"
timeout $T_BENCH python -m mjxvine.bench env $ENV --out "$RES/bench-env.json" 2>&1 | tail -6 | tee -a "$RES/gpu_check.log"
log "headline training"
timeout $T_TRAIN python -m mjxvine.train $HEADLINE --run-dir "$RES/run" > "$RES/train.log" 2>&1
log "training exit $?"
tail -40 "$RES/train.log" | tr '\r' '\n' | grep -v "^$" | tail -40 >> "$RES/gpu_check.log"
timeout 60 python -m mjxvine.export --checkpoint "$RES/run" --out "$RES/run/policy.npz" 2>&1 | tee -a "$RES/gpu_check.log"
rm -rf "$RES/run/checkpoints" "$RES/run/tb"
tar czf "$OUT/results.tgz" -C "$OUT" res
cp "$RES/gpu_check.log" "$OUT/" 2>/dev/null
cp "$RES/run/eval/results.md" "$OUT/" 2>/dev/null
log "done: $(ls "$OUT")"
