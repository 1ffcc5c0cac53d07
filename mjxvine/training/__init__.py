"""Training: SAC on any batched env, as pure compiled functions and the host loop around them.

  iteration    the pure trainer: `TrainState`, one training iteration, chunks of them
               (`lax.scan`, or the CPU host loop), members of a multi-seed or sweep run
  parallel     envs and replay split over a device mesh, gradients all-reduced
  programs     the compiled programs of a run, cached per process (trainer, evaluator)
  distributed  the collectives of a run over several processes (`jax.distributed`)
  hooks        what plugs into the loop after each chunk and at the end: fresh-start
               evaluations and the best checkpoint, logs, checkpoints, the choice
  report       the closing report: baselines, the test world, where the files are
  loop         `train(cfg, run_dir)`: the host loop, resume, stops

The command line is `python -m mjxvine.train`.
"""
