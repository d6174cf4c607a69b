"""Seeds sharded over devices (jax.sharding): 4 seeds on 4 (CPU) devices give the metrics of the
same 4 seeds on one device, and a checkpoint written on 4 devices resumes on 1."""

import csv
import os
import subprocess
import sys
import types

import jax
import pytest

from bidal_jax.train import seed_devices
from experiments import run

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TINY = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "2", "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--quiet",
    "--seeds", "4", "--checkpoint-every", "1",
]
TIMING = ("wall_time", "env_steps_per_second")


def rows(run_dir):
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return [{k: float(v) for k, v in r.items() if k not in TIMING} for r in csv.DictReader(f)]


def assert_same_metrics(a_dir, b_dir) -> None:
    """The same seeds, the same numbers up to float rounding: on one device the 4 seeds are one
    batch of the vmapped matmuls, on 4 devices each holds a batch of 1, and XLA:CPU's kernels for
    the two batch sizes round the last bits differently (measured: relative 1e-7 after 2 epochs)."""
    for a, b in zip(rows(a_dir), rows(b_dir), strict=True):
        assert a.keys() == b.keys()
        for key in a:
            exact = key.startswith(("eval_success", "train_success", "env_steps", "epoch"))
            assert a[key] == (b[key] if exact else pytest.approx(b[key], rel=1e-4, abs=1e-6)), key


def test_seeds_spread_over_as_many_devices_as_divide_them():
    devices = [types.SimpleNamespace(process_index=0, name=f"d{i}") for i in range(4)]
    assert seed_devices(8, devices) == devices
    assert seed_devices(6, devices) == devices[:2]
    assert seed_devices(1, devices) == devices[:1]
    assert seed_devices(5, devices) == devices[:1]


@pytest.mark.slow
def test_four_seeds_on_four_devices_match_one_device_and_resume_on_one(tmp_path, capsys):
    sharded, single = str(tmp_path / "sharded"), str(tmp_path / "single")
    env = {**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"}
    proc = subprocess.run([sys.executable, "-m", "experiments.run", *TINY, "--epochs", "2", "--run-dir", sharded],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "4 seed(s) on 4 device(s)" in proc.stderr
    assert jax.device_count() == 1
    assert run.main([*TINY, "--epochs", "2", "--run-dir", single]) == 0
    assert_same_metrics(sharded, single)
    # the 4-device checkpoint continues on this 1-device process
    assert run.main(["--resume", "--run-dir", sharded, "--epochs", "3", "--quiet"]) == 0
    assert "on 1 device(s)" in capsys.readouterr().err
    assert [r["epoch"] for r in rows(sharded)] == [1.0, 2.0, 3.0]
