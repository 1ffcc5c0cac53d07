"""Benchmarks: `python -m mjxvine.bench <sub-command> [--out FILE.json]`.

Each sub-command is a function `bench_X(args, cfg) -> rows` (a list of flat dicts; or
`(rows, extra)`, extra fields for the JSON) with a function `add_X_args(parser)` that adds
its own arguments, both in the sub-command's module of this package, registered in
`COMMANDS` (`mjxvine/bench/__main__.py`, the command line); `common.write_results(name,
rows, out)` prints the rows as a table and writes them to JSON together with the device,
the JAX backend, library versions, the host's CPU count and load. Add a sub-command by
writing a module with those two functions and one `COMMANDS` entry (and its rough
minutes on a 2-core CPU in `CPU_MINUTES`: `all`, and each sub-command on a CPU, first
print what they will run and about how long it takes, as estimates).

Sub-commands (module)
- all (`__main__`): every sub-command with its defaults (`--quick`: small sizes), one
  bench.json.
- physics (`physics`): env-steps/s of the batched MJX physics alone (0.1 s control
  steps), and the ratio against a Python loop over envs calling `mujoco.mj_step` (one
  thread).
- env (`env`): env-steps/s of the whole env step at the config's image size.
- update (`update`): SAC gradient steps/s at batch 128 and 512 (config image size and
  networks), the achieved GFLOP/s (XLA's cost analysis / time), this machine's matmul
  GFLOP/s (2048x2048 float32) and their ratio; `--compare` adds the program under XLA's
  default options.
- train (`train`): end-to-end `mjxvine.train` env-steps/s and gradient-steps/s while
  learning (default `experiments/fast.yaml`), per env count.
- brax (`brax_envs`): brax's own SAC and mjxvine's SAC with one schedule on the
  vector-observation vineyard task (`VectorObsEnv`), scored by brax's `Evaluator`; env
  steps and wall-clock to a common success rate, as ratios.
- depth (`depth`): images/s of `depth.render_depth` (vmapped over a batch of robot poses
  in one vineyard) for batch sizes 1, 16, 64, 256 (and 1024, 4096 on an accelerator) at
  112x112 and 64x64, compile time apart, agreement with `mujoco.mj_multiRay` on one
  image, and the ratio against the naive baseline (`mjx.ray` vmapped over every pixel; it
  ignores heightfields and cylinders in MJX 3.x, so it renders less than we do). On CPU,
  batches above 16 are also timed in `lax.map` chunks of 16. Each row gives wall-clock
  images/s and CPU ms per image (all threads): on a shared machine the latter is the
  steadier number.
- deploy (`deploy`): single-decision latency (median, p99 over 1,000 calls) of the
  exported actor (random weights, config image size) with `NumpyPolicy` and onnxruntime,
  at 1 and 2 threads, beside the paper's TF (2.8-6.2 ms) and TFLite (0.63-1.96 ms)
  figures.

Shared by all (`common`): `environment`, `write_results`, the timing of compiled
programs (`time_call`, `time_compiled`, `cost_analysis`) and the argparse types.
"""
