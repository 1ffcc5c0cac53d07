"""Evaluation of trained policies: the paper's protocol and suite, the sweeps, the fresh-start
checks of training, the checkpoint choice on validation worlds, and videos of runs.

  policies   evaluation policies: oracle, random, a run directory's or a .npz's actor
  geometry   lane geometry in numpy: distances, offsets and progress along a centreline
  rollout    batched rollouts from the lanes' starts: the cases, the protocol's stepping
  metrics    a group of runs -> success, MAE/RMSE, lane covered, v and w statistics
  report     results.md (beside the paper's numbers), trajectories.png, results.json
  paper      the paper's tests as data, and the paper's own figures
  suite      the paper's whole evaluation of one policy in one report
  sweeps     the noise and robot tables of `evaluate --sweep`
  starts     deterministic evaluation from fresh random starts (the trainer's check)
  choice     the checkpoint chosen on validation worlds, and the ranking rules
  video      videos of evaluation runs (MuJoCo's renderer)

Nothing is imported here: `from mjxvine.evaluation import rollout` loads what it needs.
"""
