"""The GPU script rehearsed on the CPU at a tiny size (`TINY=1`), so that a lent GPU finds
every step working: the vmapped training with each member's choice on validation worlds,
then the paper's suite of the chosen policy."""

import os
import subprocess
import tarfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow  # a tiny training, its choice and a suite: minutes on a 2-core CPU
def test_gpu_check_rehearsal_runs_every_step(tmp_path):
  out = tmp_path / "gpu"
  env = {**os.environ, "TINY": "1", "OUT": str(out)}
  subprocess.run(["bash", str(ROOT / "scripts" / "gpu_check.sh")], cwd=ROOT, env=env,
                 check=True, timeout=1500, capture_output=True)
  log = (out / "gpu_check.log").read_text()
  assert "training: exit 0" in log, log
  assert "member 0 chose" in log, log
  assert "suite of member 0: exit 0" in log, log
  run = out / "res" / "jackal-seeds"
  assert (run / "selected_members" / "member0.npz").is_file()
  report = out / "res" / "suite-member0" / "report.md"
  assert "selected_members/member0.npz" in report.read_text()
  with tarfile.open(out / "results.tgz") as tar:
    names = tar.getnames()
  assert "res/suite-member0/report.json" in names
  assert not any("/checkpoints/" in n for n in names)  # packed without checkpoints
