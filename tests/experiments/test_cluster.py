"""Grids through Ray (experiments/cluster.py) on a local Ray of 2 CPUs: a 2-cell tiny grid fills both run folders,
and a cell whose worker is killed mid-run is retried, resumes from its checkpoint with its replay buffer and ends
with every epoch's row exactly once; the progress table and the option checks without Ray."""

import argparse
import contextlib
import io
import json
import os
import re
import signal
import sys
import threading
import time

import pytest

from bidal_jax.config import ConfigError
from bidal_jax.run import metrics
from experiments import cluster
from experiments.bench import sweep
from experiments.paper import grid
from tests.helpers import rows

ray = pytest.importorskip("ray")

EPOCHS = 3
TINY_ARM = {"env": "planar_reach", "agent": "proprio_baseline", "num_envs": 4, "cycles_per_epoch": 2,
            "updates_per_cycle": 2, "batch_size": 8, "buffer_episodes": 8, "eval_envs": 4, "seeds": 1,
            "epochs": EPOCHS, "checkpoint_every": 1}


def ray_args(**given) -> argparse.Namespace:
    """The options of an experiment run with `--ray` on CPUs (`cluster.add_options`, `grid.add_training_options`)."""
    parser = argparse.ArgumentParser()
    grid.add_training_options(parser)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(["--ray", "--gpus-per-cell", "0", "--progress-every", "1", "--quiet"])
    return argparse.Namespace(**{**vars(args), **given})


def arm(run_dir, seed: int) -> grid.Arm:
    return grid.Arm(f"planar_reach/seed{seed}", {**TINY_ARM, "seed": seed, "run_dir": str(run_dir)})


def epochs(run_dir) -> list[int]:
    return [int(r["epoch"]) for r in rows(run_dir)]


@pytest.fixture(scope="module")
def local_ray():
    """A local Ray of 2 CPUs for this module's grids (`cluster.run_cells` leaves a running Ray as it is)."""
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=True)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def filled(local_ray, tmp_path_factory):
    """A 2-cell grid (two seeds of a tiny planar_reach run) trained through Ray: its arms and exit code."""
    out = tmp_path_factory.mktemp("grid")
    arms = [arm(out / "a", 0), arm(out / "b", 1)]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = grid.train_arms(arms, grid.make_envs(arms), ray_args())
    return arms, code, printed.getvalue()


@pytest.mark.slow
def test_a_two_cell_grid_fills_both_run_folders(filled):
    arms, code, printed = filled
    assert code == 0
    for a in arms:
        assert epochs(a.run_dir) == list(range(1, EPOCHS + 1))
        assert grid.latest(a) == EPOCHS and grid.loaded(a.run_dir)["config"]["fresh_buffer_epochs"] == []
    assert rows(arms[0].run_dir) != rows(arms[1].run_dir)  # two cells, not one run twice
    assert len(re.findall(r"^planar_reach/seed\d: done in \d+ s$", printed, re.M)) == 2
    assert re.search(r"^grid: \d+ s of wall time for 2 cell\(s\) taking \d+ s together \(wall / sum: "
                     r"\d+\.\d\d×\)$", printed, re.M)


def train_paused_once(payload) -> int:
    """`grid.train_cell` in a Ray worker whose first attempt, once epoch 2's row is written and checkpoint 1 is on
    disk (it is written while epoch 2 trains; before checkpoint 2), writes its PID into FOLDER/paused and waits to
    be killed; every attempt appends the epoch of the latest checkpoint it starts from to FOLDER/attempts."""
    cell, folder = payload
    first = not os.path.exists(os.path.join(folder, "attempts"))
    with open(os.path.join(folder, "attempts"), "a") as f:
        f.write(f"{grid.latest(cell[0])}\n")
    if first:
        write = metrics.MetricsLog.write

        def write_then_pause(log, row):
            write(log, row)
            if row["epoch"] == 2:
                deadline = time.time() + 120
                while grid.latest(cell[0]) != 1 and time.time() < deadline:
                    time.sleep(0.05)
                with open(os.path.join(folder, "paused"), "w") as f:
                    f.write(str(os.getpid()))
                time.sleep(600)

        metrics.MetricsLog.write = write_then_pause
    return grid.train_cell(cell)


def kill_when_paused(folder: str, killed: list) -> None:
    """SIGKILL the worker that `train_paused_once` paused (its PID in FOLDER/paused), once it has."""
    paused = os.path.join(folder, "paused")
    deadline = time.time() + 300
    while not os.path.exists(paused) or not open(paused).read():
        if time.time() > deadline:
            return
        time.sleep(0.1)
    pid = int(open(paused).read())
    os.kill(pid, signal.SIGKILL)
    killed.append(pid)


@pytest.mark.slow
def test_a_killed_worker_resumes_its_cell_from_its_checkpoint_with_its_buffer(filled, tmp_path):
    """The worker is killed with epoch 2's row written and checkpoint 1 on disk; the retried cell resumes from
    checkpoint 1 with its replay buffer (no `fresh_buffer_epochs`), cuts epoch 2's row and ends with every epoch's
    row exactly once: the rows of the uninterrupted run of the same arm (the 2-cell grid's first cell)."""
    uninterrupted = filled[0][0]
    resumed = arm(tmp_path / "run", 0)
    killed: list[int] = []
    killer = threading.Thread(target=kill_when_paused, args=(str(tmp_path), killed))
    killer.start()
    cells = [cluster.Cell(resumed.name, EPOCHS, ((resumed, False), str(tmp_path)),
                          lambda: cluster.epochs_done(resumed.run_dir))]
    code = cluster.run_cells(cells, train_paused_once, ray_args(retries=1))
    killer.join()
    assert killed and code == 0
    assert (tmp_path / "attempts").read_text().split() == ["None", "1"]  # fresh, then from checkpoint 1
    assert epochs(resumed.run_dir) == list(range(1, EPOCHS + 1))
    assert grid.loaded(resumed.run_dir)["config"]["fresh_buffer_epochs"] == []
    assert rows(resumed.run_dir) == rows(uninterrupted.run_dir)  # bit-identical on CPU: the buffer was restored


@pytest.mark.slow
def test_sweep_variants_train_at_once_and_their_rows_land_in_out_in_order(local_ray, tmp_path):
    out = tmp_path / "sweep.jsonl"
    tiny = "num_envs=4,cycles_per_epoch=2,batch_size=8,buffer_episodes=8,eval_envs=4"
    variants = [f"{tiny},updates_per_cycle=2", f"{tiny},updates_per_cycle=3"]
    argv = ["--env", "planar_reach", "--agent", "proprio_baseline", "--seeds", "1", "--epochs", "2", "--out", str(out),
            "--ray", "--gpus-per-cell", "0", "--progress-every", "1"]
    assert sweep.main([*argv, *(a for v in variants for a in ("--variant", v))]) == 0
    rows_out = [json.loads(line) for line in out.read_text().splitlines()]
    assert [(r["variant"], r["epoch"]) for r in rows_out] == [(v, e) for v in variants for e in (1, 2)]
    # 2 cycles an epoch of each variant's own updates per cycle
    assert [r["updates_per_seed"] for r in rows_out] == [4, 8, 6, 12]
    assert not os.path.exists(f"{out}.parts")


def test_progress_table_gives_each_cells_epochs_and_the_etas_from_the_pace_so_far():
    cells = [cluster.Cell(name, 10, None, lambda: 0) for name in ("a", "b", "c")]
    states = dict.fromkeys("abc", "queued or training")
    table = cluster.progress_table(cells, {"a": 10, "b": 4, "c": 0}, states, 120.0, {"a": 0, "b": 0, "c": 0})
    lines = table.splitlines()
    # 14 epochs by 2 cells in 120 s: 120 × 2 / 14 s per epoch of a cell; the grid: 16 epochs left at 14 per 120 s
    assert lines[2] == "| a | queued or training | 10 of 10 | 0 s |"
    assert lines[3] == "| b | queued or training | 4 of 10 | 1.7 min |"  # 6 × 17.1 s
    assert lines[4] == "| c | queued or training | 0 of 10 | 2.9 min |"
    assert lines[5] == "grid: 14 of 30 epochs after 2.0 min; ETA 2.3 min"
    unknown = cluster.progress_table(cells, dict.fromkeys("abc", 1), states, 5.0, dict.fromkeys("abc", 1))
    assert unknown.splitlines()[-1] == "grid: 3 of 30 epochs after 5 s; ETA —"


def test_the_grid_reports_its_wall_time_against_its_cells_summed_time():
    line = cluster.efficiency_line({"a": 300.0, "b": 100.0}, 220.0)
    assert line == "grid: 220 s of wall time for 2 cell(s) taking 400 s together (wall / sum: 0.55×)"
    assert cluster.efficiency_line({}, 3.0).endswith("(wall / sum: —)")


def test_a_cell_after_a_failed_one_does_not_run():
    ran = []
    assert cluster.run_cell(ran.append, "x", (0, 5.0), (2, 1.0)) == (2, 0.0) and ran == []
    code, took = cluster.run_cell(lambda payload: 0, "x", (0, 5.0))
    assert code == 0 and took >= 0.0


@pytest.mark.parametrize("option, value, expected", [
    ("gpus_per_cell", 1.5, "--gpus-per-cell 1.5: must be 0, a fraction of one GPU or a whole number"),
    ("gpus_per_cell", -1.0, "--gpus-per-cell -1"),
    ("retries", -1, "--retries -1: must be at least 0"),
    ("progress_every", 0.0, "--progress-every 0: must be positive"),
])
def test_bad_ray_options_are_refused(option, value, expected):
    with pytest.raises(ConfigError, match=expected):
        cluster.check_options(ray_args(**{option: value}))


def test_a_fraction_of_a_gpu_limits_the_workers_jax_memory():
    assert cluster.worker_env(0.5)["XLA_PYTHON_CLIENT_MEM_FRACTION"] == "0.45"
    assert "XLA_PYTHON_CLIENT_MEM_FRACTION" not in cluster.worker_env(1.0)
    assert cluster.worker_env(0)["PYTHONPATH"].split(os.pathsep)[0] == cluster.ROOT


def test_ray_without_the_extra_is_refused(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as where the cluster extra is not installed
    cells = [cluster.Cell("a", 1, None, lambda: 0)]
    with pytest.raises(ConfigError, match=r'--ray needs Ray: pip install -e "\.\[cluster\]"'):
        cluster.run_cells(cells, lambda payload: 0, ray_args())
