"""Two processes on localhost (CPU backend, one device each) train one run with
`--distributed` (jax.distributed): both finish, the logs are written once (by process 0),
and the metrics equal those of one process with 2 forced host devices. The run evaluates
during training and restores the best checkpoint for the closing report: collectives that
every process must enter."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # minutes on 2 cores: `pytest -m slow` (CI runs it)

ROOT = Path(__file__).resolve().parent.parent
SETS = ["camera.width=36", "camera.height=36", "env.num_envs=2", "env.max_steps=30",
        "sac.batch_size=16", "sac.buffer_size=512", "sac.warmup_steps=20",
        "sac.hidden=16", "sac.conv_features=4", "train.iters_per_chunk=10",
        "world.pool_size=1", "world.train_length_m=6", "eval.runs_after_train=0",
        "train.total_env_steps=60", "train.eval_every_chunks=2", "train.eval_starts=2"]
# what depends on the clock, not on the computation
TIMING = ("sps", "ups", "chunk_s", "compile_s", "wall")


def _cmd(run, *extra):
  argv = [sys.executable, "-m", "mjxvine.train", "--config", "experiments/smoke.yaml",
          "--out", str(run), *extra]
  for s in SETS:
    argv += ["--set", s]
  return argv


def _env(devices):
  return dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu",
              XLA_FLAGS=f"--xla_force_host_platform_device_count={devices}")


def _rows(run):
  return [{k: v for k, v in json.loads(l).items() if k not in TIMING}
          for l in (run / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
  root = tmp_path_factory.mktemp("dist")
  with socket.socket() as s:
    s.bind(("localhost", 0))
    port = s.getsockname()[1]
  procs = [subprocess.Popen(
      _cmd(root / "two", "--distributed", "--coordinator", f"localhost:{port}",
           "--num-processes", "2", "--process-id", str(i)),
      cwd=ROOT, env=_env(1), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
      for i in range(2)]
  outs = []
  try:
    for p in procs:
      outs.append(p.communicate(timeout=1800))
  finally:
    for p in procs:
      if p.poll() is None:
        p.kill()
  single = subprocess.run(_cmd(root / "one"), cwd=ROOT, env=_env(2), capture_output=True,
                          text=True, timeout=1800)
  return root, [p.returncode for p in procs], outs, single


def test_two_processes_finish_and_log_once(runs):
  root, codes, outs, _ = runs
  assert codes == [0, 0], "\n".join(err[-2000:] for _, err in outs)
  # process 0 prints the summary and the progress; process 1 is silent
  assert json.loads(outs[0][0].strip().splitlines()[-1])["env_steps"] == 60
  # (gloo, JAX's CPU collectives, says on stdout that the ranks are connected)
  assert not [l for l in outs[1][0].splitlines() if l.strip() and not l.startswith("[Gloo]")]
  assert "over 2 processes" in outs[0][1]
  assert not any(l.startswith(("run ", "evaluated", "best policy", "wrote"))
                 for l in outs[1][1].splitlines())
  assert [r["chunk"] for r in _rows(root / "two")] == [1, 2, 3]
  assert len(list((root / "two" / "tb").glob("events.out.tfevents.*"))) == 1
  assert (root / "two" / "best.json").is_file()


def test_two_processes_equal_one_process_with_two_devices(runs):
  root, _, _, single = runs
  assert single.returncode == 0, single.stderr[-3000:]
  assert _rows(root / "two") == _rows(root / "one")
