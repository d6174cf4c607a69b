"""Grids through Ray (experiments/cluster.py) on a local Ray of 2 CPUs: a 2-cell tiny grid fills both run folders,
and a cell whose worker is killed mid-run is retried, resumes from its checkpoint with its replay buffer and ends
with every epoch's row exactly once; the command line's local Ray listens on loopback alone, Ctrl-C stops its cell
with a checkpoint (exit 130) and the same command resumes it. Without Ray: the progress table and the option
checks; on a Ray of this process (`FakeRay`), the grid under faults: a cell failing on every try is reported once
while the others go on, Ctrl-C cancels the cells and waits for their checkpoints, a second grid on one --out is
refused, an address nothing answers is refused at once, the cells' GPUs follow the cluster's."""

import argparse
import contextlib
import io
import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import types

import pytest

from bidal_jax.config import ConfigError
from bidal_jax.run import checkpoint, metrics
from experiments import cluster
from experiments.bench import sweep
from experiments.paper import grid
from tests.helpers import REPO, rows

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
    cluster.init_ray(ray, num_cpus=2, include_dashboard=False, log_to_driver=True)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def filled(local_ray, tmp_path_factory):
    """A 2-cell grid (two seeds of a tiny planar_reach run) trained through Ray: its arms and exit code."""
    out = tmp_path_factory.mktemp("grid")
    arms = [arm(out / "a", 0), arm(out / "b", 1)]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = grid.train_arms(arms, grid.make_envs(arms), ray_args(), str(out))
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
    code = cluster.run_cells(cells, train_paused_once, ray_args(retries=1), str(tmp_path))
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
    assert cluster.run_cell(ran.append, "x", (0, 5.0, None), (2, 1.0, "error: bad")) == (
        2, 0.0, "not run: a cell it starts after failed") and ran == []
    code, took, why = cluster.run_cell(lambda payload: (0, None), "x", (0, 5.0, None))
    assert code == 0 and took >= 0.0 and why is None


def test_a_cell_whose_code_raises_fails_in_one_line_without_a_traceback():
    def bug(payload):
        raise ValueError("no such thing\nmore")

    assert cluster.run_cell(bug, "x")[::2] == (cluster.EXIT_CRASHED, "error: ValueError: no such thing")


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


def test_ray_without_the_extra_is_refused(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` fails as where the cluster extra is not installed
    cells = [cluster.Cell("a", 1, None, lambda: 0)]
    with pytest.raises(ConfigError, match=r'--ray needs Ray: pip install -e "\.\[cluster\]"'):
        cluster.run_cells(cells, lambda payload: (0, None), ray_args(), str(tmp_path))


# ----- the grid under faults, on a Ray of this process (`FakeRay`): failures, Ctrl-C, --out, addresses, GPUs -------


class WorkerDied(BaseException):
    """What a cell's `work` raises in `FakeRay` to have its worker die (as a SIGKILL or a segfault would: no Python
    exception a cell could catch)."""


class FakeRay:
    """Enough of Ray's API for `cluster.run_cells`, run in this process: a task runs when it is submitted, a worker
    that dies (`WorkerDied`) is retried up to `max_retries` times, then its result is Ray's WorkerCrashedError, and a
    task whose input failed fails alike without running. `nodes` are what `ray.nodes()` gives; `interrupts`: how many
    of the next `wait` calls raise KeyboardInterrupt (Ctrl-C)."""

    class exceptions:  # noqa: N801 - Ray's module name
        class RayError(Exception):
            pass

        class WorkerCrashedError(RayError):
            pass

    def __init__(self, nodes=({"Alive": True, "Resources": {"CPU": 2.0}},), initialized=True, interrupts=0):
        self.nodes_, self.initialized, self.interrupts = list(nodes), initialized, interrupts
        self.options, self.attempts, self.results, self.cancelled, self.waits = {}, {}, {}, [], []

    def is_initialized(self):
        return self.initialized

    def init(self, **kwargs):
        raise AssertionError(f"Ray was started: {kwargs}")

    def nodes(self):
        return self.nodes_

    def remote(self, **options):
        self.options = options

        def wrap(function):
            return types.SimpleNamespace(remote=lambda *args: self._run(function, *args))

        return wrap

    def _run(self, function, work, payload, *inputs):
        ref, upstream = object(), [self.results[i] for i in inputs]  # Ray passes a task its inputs' values
        failed = [u for u in upstream if isinstance(u, Exception)]
        if failed:
            self.attempts[ref], result = 0, failed[0]
        else:
            for attempt in range(1, self.options["max_retries"] + 2):
                self.attempts[ref] = attempt
                try:
                    result = function(work, payload, *upstream)
                    break
                except WorkerDied:
                    result = self.exceptions.WorkerCrashedError(
                        "The worker died unexpectedly while executing this task. Check python-core-worker-*.log "
                        "files for more information.")
        self.results[ref] = result
        return ref

    def wait(self, refs, num_returns=1, timeout=None):
        self.waits.append(num_returns)
        if self.interrupts:
            self.interrupts -= 1
            raise KeyboardInterrupt
        return list(refs[:num_returns]), list(refs[num_returns:])

    def get(self, ref):
        if isinstance(self.results[ref], Exception):
            raise self.results[ref]
        return self.results[ref]

    def cancel(self, ref, force=False):
        self.cancelled.append((ref, force))


def cell(name, after=()):
    return cluster.Cell(name, 1, name, lambda: 0, tuple(after))


def work_of(outcomes, ran):
    """A cell's `work` whose outcome is `outcomes[payload]`: (code, line), or `WorkerDied` raised."""
    def work(payload):
        ran.append(payload)
        if outcomes[payload] is WorkerDied:
            raise WorkerDied
        return outcomes[payload]

    return work


@pytest.fixture
def fake_ray(monkeypatch):
    """`cluster.import_ray` gives a `FakeRay` (a running one by default); the fixture sets it up."""
    def use(**kwargs):
        fake = FakeRay(**kwargs)
        monkeypatch.setattr(cluster, "import_ray", lambda local=False: fake)
        return fake

    return use


def test_a_cell_that_fails_on_every_try_is_reported_once_and_the_others_go_on(fake_ray, tmp_path, capsys):
    """b's worker dies on each of its 3 tries, c fails with its own error, d starts after b: each is reported once
    with its error as it ends, a and e train, and the grid exits with the first failure's code, listing them all."""
    fake = fake_ray()
    ran = []
    outcomes = {"a": (0, None), "b": WorkerDied, "c": (2, "error: --batch-size 0: must be a positive integer"),
                "d": (0, None), "e": (0, None)}
    cells = [cell("a"), cell("b"), cell("c"), cell("d", after=["b"]), cell("e")]
    code = cluster.run_cells(cells, work_of(outcomes, ran), ray_args(retries=2), str(tmp_path))
    out, err = capsys.readouterr()
    assert code == cluster.EXIT_LOST and ran == ["a", "b", "b", "b", "c", "e"]
    assert sorted(fake.attempts.values()) == [0, 1, 1, 1, 3]  # b: 3 tries; d: none
    assert err.splitlines() == [
        "error: b: lost (exit 5): its worker died 3 time(s) (The worker died unexpectedly while executing this task. "
        "Check python-core-worker-*.log files for more information.); run the command again to resume it from its "
        "latest checkpoint",
        "error: c: failed (exit 2): --batch-size 0: must be a positive integer",
        "error: d: not run: it starts after b, which failed",
        "error: 3 of 5 cell(s) failed: b (lost (exit 5)), c (failed (exit 2)), d (not run); the others ended",
    ]
    assert re.search(r"^a: done in \d+ s$", out, re.M) and re.search(r"^e: done in \d+ s$", out, re.M)
    assert not os.path.exists(tmp_path / cluster.GRID_LOCK)  # released


def test_ctrl_c_stops_the_cells_and_exits_130_with_one_line(fake_ray, tmp_path, capsys):
    """Ctrl-C while the grid waits: every cell still pending is cancelled (Ray raises SIGINT's handler in a running
    cell's worker: it saves a checkpoint after its epoch in flight), the grid waits for them all and exits 130; a
    second Ctrl-C while it waits cancels them at once."""
    fake = fake_ray(interrupts=1)
    cells = [cell("a"), cell("b")]
    work = work_of({"a": (0, None), "b": (0, None)}, [])
    assert cluster.run_cells(cells, work, ray_args(), str(tmp_path)) == 130
    err = capsys.readouterr().err.splitlines()
    assert [force for _, force in fake.cancelled] == [False, False] and fake.waits == [1, 2]
    assert err == ["SIGINT: stopping the cells, each after a checkpoint of its epoch in flight (Ctrl-C again stops "
                   "them at once)", "interrupted: the cells are stopped, each at its latest checkpoint; run the same "
                   "command again to resume them"]
    fake = fake_ray(interrupts=2)
    assert cluster.run_cells(cells, work, ray_args(), str(tmp_path)) == 130
    assert [force for _, force in fake.cancelled] == [False, False, True, True]
    assert capsys.readouterr().err.splitlines()[-1].startswith("interrupted: ")


def test_two_grids_on_one_out_are_refused(fake_ray, tmp_path, capsys):
    """A grid holds its --out while its cells train: a second grid on it is refused in one line, exit 2, before its
    Ray starts; once the first has ended, the folder is free."""
    fake = fake_ray(initialized=False)  # would fail the test if the refused grid started Ray
    out = tmp_path / "curves"
    with cluster.holding(str(out)):
        assert grid.train_arms([], {}, ray_args(), str(out)) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: --out {out}: another grid trains into it (host {socket.gethostname()}, PID {os.getpid()}); wait "
        "until it ends or give another --out"]
    fake.initialized = True
    assert grid.train_arms([], {}, ray_args(), str(out)) == 0


def test_an_address_nothing_answers_is_refused_in_one_line_within_30_s(fake_ray, monkeypatch, tmp_path):
    """Ray itself retries an address nothing answers for minutes; the grid refuses it at once, before `ray.init`
    (which fails this test if called), and one that answers but lets no driver join within 20 s."""
    fake_ray(initialized=False)
    with socket.socket() as s:  # a port that nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = str(tmp_path)
    began = time.time()
    with pytest.raises(ConfigError, match=rf"^--ray-address 127\.0\.0\.1:{port}: nothing answers at 127\.0\.0\.1:"
                                          rf"{port} \(Connection refused\); start the cluster there"):
        cluster.run_cells([cell("a")], work_of({"a": (0, None)}, []), ray_args(ray_address=f"127.0.0.1:{port}"), out)
    assert time.time() - began < 30

    def silent(address, timeout):
        raise TimeoutError("timed out")

    monkeypatch.setattr(cluster.socket, "create_connection", silent)
    with pytest.raises(ConfigError, match=r"nothing answers at 10\.1\.2\.3:6379 \(no answer within 5 s\)"):
        cluster.run_cells([cell("a")], work_of({"a": (0, None)}, []), ray_args(ray_address="10.1.2.3"), out)
    with pytest.raises(ConfigError, match=r"--ray-address head:port: not an address of a Ray cluster"):
        cluster.check_reachable("head:port")

    def answers(address, timeout):  # a port that accepts, but is no Ray cluster's: a driver cannot join
        return types.SimpleNamespace(close=lambda: None)

    def hangs(command, timeout, **kwargs):
        raise subprocess.TimeoutExpired(command, timeout)

    monkeypatch.setattr(cluster.socket, "create_connection", answers)
    monkeypatch.setattr(cluster.subprocess, "run", hangs)
    with pytest.raises(ConfigError, match=r"^--ray-address 10\.1\.2\.3:8000: no Ray cluster let a driver join "
                                          r"within 20 s; check that `ray start --head` runs there"):
        cluster.run_cells([cell("a")], work_of({"a": (0, None)}, []), ray_args(ray_address="10.1.2.3:8000"), out)
    assert cluster.address_of("ray://head") == ("head", 10001) and cluster.address_of("[::1]:6380") == ("::1", 6380)


@pytest.mark.parametrize("resources, asked, gpus", [({"CPU": 8.0}, None, 0.0), ({"CPU": 8.0, "GPU": 2.0}, None, 1.0),
                                                    ({"CPU": 8.0, "GPU": 2.0}, 0.5, 0.5)])
def test_cells_take_a_gpu_where_the_cluster_has_gpus_else_train_on_cpus(fake_ray, tmp_path, capsys, resources, asked,
                                                                        gpus):
    fake = fake_ray(nodes=[{"Alive": True, "Resources": resources}])
    args = ray_args(gpus_per_cell=asked)
    assert cluster.run_cells([cell("a")], work_of({"a": (0, None)}, []), args, str(tmp_path)) == 0
    assert fake.options["num_gpus"] == gpus
    assert f"Ray: each of 1 cell(s) takes {gpus:g} GPU(s) and 1 CPU(s)" in capsys.readouterr().out


@pytest.mark.parametrize("gpus, cpus, message", [
    (1.0, 1.0, r"--gpus-per-cell 1: the Ray cluster has no GPUs; its cells would wait forever \(leave "
               r"--gpus-per-cell out, or 0, to train the cells on CPUs\)"),
    (0.0, 16.0, r"--cpus-per-cell 16: the Ray cluster has 8 CPU\(s\) at most on one node; its cells would wait "
                r"forever$"),
])
def test_cells_asking_for_what_no_node_has_are_refused(fake_ray, tmp_path, gpus, cpus, message):
    fake_ray(nodes=[{"Alive": True, "Resources": {"CPU": 8.0}}, {"Alive": False, "Resources": {"CPU": 64.0,
                                                                                               "GPU": 8.0}}])
    with pytest.raises(ConfigError, match=message):
        cluster.run_cells([cell("a")], work_of({"a": (0, None)}, []), ray_args(gpus_per_cell=gpus, cpus_per_cell=cpus),
                          str(tmp_path))


GRID = ["--tasks", "planar_reach", "--agents", "proprio_baseline", "--seeds", "1", "--epochs", "300", "--ray",
        "--progress-every", "1", "--quiet", "--num-envs", "4", "--cycles-per-epoch", "2", "--updates-per-cycle", "2",
        "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--checkpoint-every", "100"]
LOOPBACK = ("127.0.0.1", "::ffff:127.0.0.1", "::1")


def listening(pid: int) -> list[tuple[str, str]]:
    """(process name, address) of every socket that the process `pid` and its descendants listen on."""
    import psutil  # Ray installs it

    found = []
    root = psutil.Process(pid)
    for process in [root, *root.children(recursive=True)]:
        with contextlib.suppress(psutil.Error):
            found += [(process.name(), c.laddr.ip) for c in process.net_connections(kind="inet")
                      if c.status == psutil.CONN_LISTEN]
    return found


def signal_masks(pid: int) -> str:
    """A process's blocked, ignored and caught signals (/proc/PID/status, hexadecimal masks: SIGINT is bit 1), which a
    child inherits across exec where blocked or ignored: what a driver that does not stop on SIGINT was given."""
    with open(f"/proc/{pid}/status", encoding="utf-8") as f:
        lines = [line.strip().replace("\t", " ") for line in f]
    return " ".join(line for line in lines if line.startswith(("SigBlk", "SigIgn", "SigCgt")))


@pytest.mark.slow
def test_a_local_grid_listens_on_loopback_stops_on_ctrl_c_and_the_same_command_resumes(tmp_path):
    """`python -m experiments.paper.curves --ray` of one 300-epoch cell: while it trains, every socket its local Ray
    listens on is on loopback; SIGINT to the grid's process once epoch 3 is written stops the cell with a checkpoint
    at its last epoch and exits 130 with one line; the same command resumes it, and the run ends with every epoch's
    row once, its replay buffer restored."""
    command = [sys.executable, "-m", "experiments.paper.curves", *GRID, "--out", str(tmp_path / "curves")]
    run_dir = tmp_path / "curves" / "planar_reach" / "proprio_baseline"
    driver = subprocess.Popen(command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 240
        while not (run_dir / "metrics.csv").exists() or len((run_dir / "metrics.csv").read_text().splitlines()) < 4:
            assert time.time() < deadline and driver.poll() is None, driver.stderr.read()
            time.sleep(0.1)
        sockets = listening(driver.pid)
        masks = signal_masks(driver.pid)
        driver.send_signal(signal.SIGINT)
        err = driver.communicate(timeout=120)[1]
    finally:
        driver.kill()
    assert "gcs_server" in [name for name, _ in sockets] and all(ip in LOOPBACK for _, ip in sockets), sockets
    assert driver.returncode == 130, f"{masks} (this worker: {signal_masks(os.getpid())})\n{err}"
    own = [line for line in err.splitlines() if not line.startswith("\x1b") and not line.startswith("(")]
    assert [line for line in own if line.startswith(("interrupted", "error"))] == [
        "interrupted: the cells are stopped, each at its latest checkpoint; run the same command again to resume them"
    ] and "Traceback" not in err, err
    stopped = checkpoint.latest_step(str(run_dir / "checkpoints"))
    assert 3 <= stopped < 300 and epochs(run_dir)[-1] == stopped  # saved after the epoch in flight
    again = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert epochs(run_dir) == list(range(1, 301)) and grid.loaded(str(run_dir))["config"]["fresh_buffer_epochs"] == []
