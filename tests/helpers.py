"""Helpers that several test modules share (the fixtures are conftest.py's)."""

import csv
import dataclasses
import hashlib
import os

import pytest

import envs_mjx
from bidal_jax.config import Config
from bidal_jax.run import checkpoint, loop
from experiments import run

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# a tiny planar_reach run of the proprio baseline: compiles in seconds
TINY = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "2", "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--quiet",
]
# 4 seeds, a checkpoint every epoch: the runs spread over devices and processes
SHARDED = [*TINY, "--seeds", "4", "--checkpoint-every", "1"]
TIMING = ("wall_time", "wall_time_with_compile", "env_steps_per_second")


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




def snapshot(root) -> dict | None:
    """Every path under `root` with its mtime, size and content hash (None if `root` does not exist); not
    `root`'s own mtime, which a run refused after it locked the directory changes (it adds and deletes `.lock`)."""
    if not os.path.exists(root):
        return None
    found = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = os.path.join(dirpath, name)
            st = os.stat(path)
            content = hashlib.sha1(open(path, "rb").read()).hexdigest() if name in filenames else None
            found[os.path.relpath(path, root)] = (st.st_mtime_ns, st.st_size, content)
    return found


def main_exit_code(argv) -> int:
    try:
        return run.main(argv)
    except SystemExit as exit_:  # argparse's own errors
        return exit_.code


def assert_refused(argv, run_dir, expected: list, capsys) -> None:
    """main(argv) exits 2 with one `error:` line holding every `expected` string (a tuple: one of
    its strings), and leaves `run_dir` as it was."""
    before = snapshot(run_dir)
    assert main_exit_code(argv) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error: " in line]
    assert len(errors) == 1, err
    for text in expected:
        assert any(t in errors[0] for t in ((text,) if isinstance(text, str) else text)), (text, errors[0])
    assert snapshot(run_dir) == before


def restored_state(run_dir, step=None):
    """(the whole TrainState of a checkpoint of the run in `run_dir`, the latest by default; its epoch)."""
    saved = Config.from_dict(checkpoint.read_config(os.path.join(run_dir, "checkpoints")), str(run_dir))
    config = dataclasses.replace(saved, run=dataclasses.replace(saved.run, run_dir=str(run_dir)))
    return loop.restore_state(envs_mjx.make(config.run.env, render=False), config, step)

# the run of the `finished` fixture (conftest.py): a tiny proprio baseline run, checkpointed after every epoch
FINISHED_SEEDS, FINISHED_EPOCHS = 2, 4
FINISHED = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "4", "--batch-size", "16", "--buffer-episodes", "8", "--eval-envs", "16", "--quiet",
    "--seeds", str(FINISHED_SEEDS), "--epochs", str(FINISHED_EPOCHS), "--checkpoint-every", "1",
]
