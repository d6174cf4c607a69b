"""Cells of a grid scheduled through Ray (`--ray`): the paper's experiments and `experiments.bench.sweep`.

A cell is one unit of a grid (a paper experiment's run, a sweep's variant) that a Ray task trains on its share of
a machine: `--gpus-per-cell` GPUs (by default 1 where the Ray cluster has GPUs, else 0: the cells train on CPUs; a
fraction, e.g. 0.5, lets cells small enough share one GPU) and `--cpus-per-cell` CPUs. Ray starts a local instance
on this machine unless `--ray-address` names a running cluster (`ray start --head` prints its address); `ray.init`
run by the caller beforehand is used as it is.

- A local Ray (`start_ray`) listens on the loopback interface alone (Ray binds its servers to 127.0.0.1 where it
  takes the node's address to be loopback, as it does on macOS and Windows: `LOCAL_RAY`), with Ray's token
  authentication on where the installed Ray has it; a `--ray-address` that nothing answers, or that a Ray driver
  cannot join, is refused in one line within 30 s (`check_reachable`, `check_joinable`) rather than retried by Ray
  for minutes. Cells that ask for GPUs (or CPUs) no node of the
  cluster has, which Ray would keep waiting for, are refused in one line (`check_fits`).
- One grid at a time per `--out`: the grid locks it (`holding`, a lock file there) while its cells train; a second
  grid on it is refused (exit 2) before Ray starts.
- Results: a cell writes where the experiment's `--out` says, as it does without Ray (a run folder: config.json,
  metrics.csv, checkpoints); on a cluster `--out` is a path that every node sees.
- A worker that dies (a node lost, the process killed) has its cell retried, up to `--retries` times: a run folder
  resumes from its own latest checkpoint with its replay buffer, as running the experiment again does.
- Failures: a cell that fails (its exit code, or a worker that died on every try) is reported once, in one line with
  its error, as it ends; the other cells go on; at the end one line lists the cells that failed.
- Ctrl-C stops the cells: each running one saves a checkpoint after its epoch in flight (Ray's cancel raises SIGINT's
  handler in its worker, as Ctrl-C in `experiments.run` does), the grid waits for them and exits 130 (a second
  Ctrl-C stops them at once; their latest checkpoints are kept). The same command resumes every cell.
- Progress: every `--progress-every` seconds a table of the cells with their epochs done (each cell's metrics.csv
  through `report.load_run`, or the `progress` its caller reads) and an ETA, the grid's from its pace so far. As
  each cell ends, the seconds it took in its worker; at the end, the grid's wall time against their sum.
- Each worker process trains one cell and exits (`max_calls=1`), so that the GPU Ray gives it is the one its JAX
  sees and its memory goes back when the cell ends; a cell given a fraction of a GPU lets JAX take that fraction
  of the GPU's memory (`XLA_PYTHON_CLIENT_MEM_FRACTION`, where its default takes 75 %). Workers import this
  checkout's packages (`PYTHONPATH`); on a cluster every node has the project installed (`pip install -e
  ".[cluster]"`), or reads it from the shared path.

Ray is an extra: `pip install -e ".[cluster]"`; without it `--ray` is refused with one `error:` line. Exit code of
a grid: the first failing cell's in the grid's order (`experiments.cli.exit_code`; `EXIT_LOST` when a cell's worker
died more than `--retries` times, `EXIT_CRASHED` for a cell whose code raised an error no exit code names), else
0; 2 when the grid is refused before its cells start (an option, an address that does not answer, an `--out`
another grid holds); 130 when Ctrl-C stopped it. Unlike the sequential path, a failing cell does not stop the
others.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import os
import socket
import subprocess
import sys
import time
import urllib.parse
import warnings
from typing import Any, Callable, Iterator, Sequence

import experiments
from bidal_jax.config import ConfigError
from bidal_jax.run import memory, rundir
from bidal_jax.run.runfiles import first_line
from experiments import report

EXIT_LOST = 5  # a cell's worker died more often than --retries allows
EXIT_CRASHED = 1  # a cell whose code raised an error that no exit code names (a bug): Python's exit code for it
EXIT_SIGINT = 130  # the driver stopped by Ctrl-C, as experiments.run's
# the folder holding the packages, which workers put first on their path (this checkout's code, not another)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(experiments.__file__)))
GRID_LOCK = ".grid.lock"  # the lock file in a grid's --out folder (`holding`; a sweep's: beside its --out file)
CONNECT_TIMEOUT = 5.0  # seconds a --ray-address has to accept a connection before the grid is refused
JOIN_TIMEOUT = 20.0  # seconds a Ray driver has to join it (`check_joinable`): both together stay under 30 s
# what `check_joinable` runs in a child process: join the cluster at argv[1] and leave it
JOIN = ("import sys, ray; ray.init(address=sys.argv[1], include_dashboard=False, log_to_driver=False, "
        "logging_level=40); ray.shutdown()")
# the environment of a local Ray that a grid starts, unless already set: its servers on loopback alone (Ray takes
# the node's address to be 127.0.0.1 where clusters are off, and then binds to it) and Ray's token authentication on
LOCAL_RAY = {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_AUTH_MODE": "token"}
RAY_PORTS = {"ray": 10001}  # the default port of an address by its scheme (Ray Client's); else the GCS's
GCS_PORT = 6379


@dataclasses.dataclass(frozen=True)
class Cell:
    """One cell of a grid: its name, its `epochs`, what its task is given (`payload`), the cells that must end
    first (`after`, by name: a transfer arm after its source) and how to read the epochs it has done
    (`progress()`, e.g. `epochs_done` of its run folder)."""

    name: str
    epochs: int
    payload: Any
    progress: Callable[[], int]
    after: tuple[str, ...] = ()


def add_options(parser: argparse.ArgumentParser) -> None:
    """The Ray options of a command whose cells Ray may schedule."""
    group = parser.add_argument_group("Ray (pip install -e \".[cluster]\"): the cells as tasks, on every GPU of a "
                                      "machine or a cluster")
    group.add_argument("--ray", action="store_true",
                       help="schedule the cells through Ray: a local Ray on this machine unless --ray-address")
    group.add_argument("--ray-address", default=None, metavar="ADDRESS",
                       help="join the Ray cluster at ADDRESS (`ray start --head` prints it; 'auto': the one running "
                       "on this machine); implies --ray")
    group.add_argument("--gpus-per-cell", type=float, default=None,
                       help="GPUs each cell takes: 1, or a fraction (0.5: two cells share a GPU), or 0: on CPUs "
                       "(default: 1 where the Ray cluster has GPUs, else 0)")
    group.add_argument("--cpus-per-cell", type=float, default=1.0, help="CPUs each cell takes (default: 1)")
    group.add_argument("--retries", type=int, default=3,
                       help="times a cell whose worker dies is retried, from its latest checkpoint (default: 3)")
    group.add_argument("--progress-every", type=float, default=60.0,
                       help="seconds between progress tables (default: 60)")


def wanted(args: argparse.Namespace) -> bool:
    """Whether the command line asks for Ray (`--ray`, or `--ray-address`)."""
    return bool(args.ray or args.ray_address)


def check_options(args: argparse.Namespace) -> None:
    """ConfigError, one line, for a Ray option Ray would refuse or that makes no sense."""
    gpus = args.gpus_per_cell
    if gpus is not None and not (gpus >= 0 and (gpus <= 1 or float(gpus).is_integer())):
        raise ConfigError(f"--gpus-per-cell {gpus:g}: must be 0, a fraction of one GPU or a whole number")
    if not args.cpus_per_cell >= 0:
        raise ConfigError(f"--cpus-per-cell {args.cpus_per_cell:g}: must be at least 0")
    if args.retries < 0:
        raise ConfigError(f"--retries {args.retries}: must be at least 0")
    if not args.progress_every > 0:
        raise ConfigError(f"--progress-every {args.progress_every:g}: must be positive")


def prepare_driver(args: argparse.Namespace) -> None:
    """Before anything touches a device: with Ray asked for, check its options (`check_options`) and keep this
    process's JAX on the CPU (it only builds envs for the plan; the GPUs are the cells'); without, the runs train in
    this process: where other processes hold its GPU, JAX takes what is free of it (`memory.share_gpu`)."""
    if wanted(args):
        check_options(args)
        import jax

        jax.config.update("jax_platforms", "cpu")
    else:
        memory.share_gpu()


def epochs_done(run_dir: str) -> int:
    """The last epoch of a run folder's metrics.csv (`report.load_run`); 0 while it has none."""
    try:
        return int(report.load_run(run_dir)["epoch"][-1])
    except report.RunError:
        return 0


def worker_env(gpus_per_cell: float) -> dict[str, str]:
    """The environment variables of a cell's worker: this checkout's packages first on its path, XLA's C++ logs as
    the command line has them (off unless TF_CPP_MIN_LOG_LEVEL says otherwise: `experiments`), and with a fraction
    of a GPU, JAX's share of the GPU's memory."""
    env = {"PYTHONPATH": os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p),
           "TF_CPP_MIN_LOG_LEVEL": os.environ.get("TF_CPP_MIN_LOG_LEVEL", "3")}
    if 0 < gpus_per_cell < 1:
        env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{memory.FULL_GPU_FRACTION * gpus_per_cell:.2f}"
    return env


def duration(seconds: float | None) -> str:
    """"—" for an unknown time, else "42 s", "12.5 min" or "2.4 h"."""
    if seconds is None:
        return "—"
    return f"{seconds:.0f} s" if seconds < 60 else f"{seconds / 60:.1f} min" if seconds < 3600 \
        else f"{seconds / 3600:.1f} h"


def progress_table(cells: Sequence[Cell], done: dict[str, int], states: dict[str, str], elapsed: float,
                   start: dict[str, int]) -> str:
    """Markdown: per cell its state, epochs done of its epochs (`done`) and its ETA; then the grid's epochs and
    ETA, both from the pace of the epochs done since the grid started (`start`: each cell's epochs then; a cell's
    ETA is its remaining epochs at the grid's mean pace per cell that has progressed)."""
    new = {c.name: done[c.name] - start[c.name] for c in cells}
    moving = sum(1 for n in new.values() if n > 0)
    per_epoch = elapsed * moving / sum(new.values()) if moving else None  # seconds per epoch of one cell

    def eta(cell: Cell) -> float | None:
        left = max(cell.epochs - done[cell.name], 0)
        return 0.0 if left == 0 else None if per_epoch is None else left * per_epoch

    rows = [[c.name, states[c.name], f"{done[c.name]} of {c.epochs}", duration(eta(c))] for c in cells]
    total, reached = sum(c.epochs for c in cells), sum(min(done[c.name], c.epochs) for c in cells)
    gained = sum(new.values())
    grid_eta = 0.0 if reached == total else elapsed * (total - reached) / gained if gained else None
    return "\n".join([
        report.markdown_table(["cell", "state", "epochs", "ETA"], rows),
        f"grid: {reached} of {total} epochs after {duration(elapsed)}; ETA {duration(grid_eta)}",
    ])


def run_cell(work: Callable[[Any], tuple[int, str | None]], payload: Any,
             *upstream: tuple[int, float, str | None]) -> tuple[int, float, str | None]:
    """A cell's task: (`work(payload)`'s exit code, the seconds it took in the worker, the one line saying why it
    failed or None), or, without running it, (the first nonzero code of the cells it comes `after`, 0.0, "not run:
    ...") (`upstream`: their results). An error of `work` that no exit code names (a bug) is `EXIT_CRASHED` with its
    type and first line, not a traceback (nor a retry: only a worker that dies is retried)."""
    failed = next((code for code, _, _ in upstream if code), 0)
    if failed:
        return failed, 0.0, "not run: a cell it starts after failed"  # (`_drive` names it)
    began = time.perf_counter()
    try:
        code, why = work(payload)
    except Exception as err:
        code, why = EXIT_CRASHED, f"error: {type(err).__name__}: {first_line(err)}"
    return code, time.perf_counter() - began, why


def efficiency_line(seconds: dict[str, float], wall: float) -> str:
    """The grid's wall time against the sum of its cells' own times (what running them one after another in
    one process would about take): how much running them at once saved."""
    total = sum(seconds.values())
    ratio = f"{wall / total:.2f}×" if total > 0 else "—"
    return (f"grid: {wall:.0f} s of wall time for {len(seconds)} cell(s) taking {total:.0f} s together "
            f"(wall / sum: {ratio})")


def address_of(address: str) -> tuple[str, int]:
    """(host, port) of a `--ray-address`: HOST:PORT, [IPV6]:PORT or ray://HOST:PORT (Ray Client); without a port,
    Ray's default (`GCS_PORT`, or Ray Client's). ConfigError for one that is neither."""
    scheme, _, rest = address.rpartition("://")
    try:
        parsed = urllib.parse.urlsplit(f"//{rest}")
        port = parsed.port
    except ValueError:
        port, parsed = None, None
    if parsed is None or not parsed.hostname:
        raise ConfigError(f"--ray-address {address}: not an address of a Ray cluster (HOST:PORT, as `ray start "
                          "--head` prints it, or 'auto')")
    return parsed.hostname, port or RAY_PORTS.get(scheme, GCS_PORT)


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT) -> None:
    """ConfigError, one line, when nothing accepts a connection at `address` (`address_of`) within `timeout`
    seconds (refused, unreachable, an unknown host): Ray itself would retry it for minutes."""
    host, port = address_of(address)
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as err:
        why = f"no answer within {timeout:.0f} s" if isinstance(err, TimeoutError) else err.strerror or str(err)
        raise ConfigError(f"--ray-address {address}: nothing answers at {host}:{port} ({why}); start the cluster "
                          "there (`ray start --head`), or leave --ray-address out for a local Ray") from None


def check_joinable(address: str, timeout: float = JOIN_TIMEOUT) -> None:
    """ConfigError, one line, when a Ray driver cannot join the cluster at `address` within `timeout` seconds: tried
    in a child process (killed at the timeout), since `ray.init` keeps retrying an address that answers but is no
    Ray cluster's (or one it maps to another of this machine's addresses) for minutes, printing its warnings."""
    try:
        done = subprocess.run([sys.executable, "-c", JOIN, address], capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise ConfigError(f"--ray-address {address}: no Ray cluster let a driver join within {timeout:.0f} s; check "
                          "that `ray start --head` runs there and prints this address (a cluster with token "
                          "authentication needs RAY_AUTH_MODE=token here too)") from None
    if done.returncode:
        last = next((line.strip() for line in reversed(done.stderr.splitlines()) if line.strip()), "")
        raise ConfigError(f"--ray-address {address}: Ray could not join the cluster ({last or done.returncode})")


def import_ray(local: bool = False):
    """The `ray` module, imported with `LOCAL_RAY`'s settings where unset when it is to start a `local` Ray (Ray
    reads them as it is imported, and its processes inherit them); ConfigError when the extra is not installed."""
    if local:
        for name, value in LOCAL_RAY.items():
            os.environ.setdefault(name, value)
    try:
        import ray
    except ImportError:
        raise ConfigError("--ray needs Ray: pip install -e \".[cluster]\"") from None
    return ray


def init_ray(ray, **options) -> None:
    """`ray.init(**options)` without JAX's warning about a fork in a threaded process: Ray starts its servers with
    `subprocess.Popen` and a `preexec_fn` (signal masks, death signal), which runs in the forked child only until it
    execs the server, and no JAX runs there; the warning is JAX's at-fork hook, raised for every fork."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        ray.init(**options)


def start_ray(ray, address: str | None) -> None:
    """Join the Ray cluster at `address` (checked first, in 30 s at most: `check_reachable`, `check_joinable`; 'auto':
    the one running on this machine), or start a local one; ConfigError, one line, when Ray cannot."""
    if address and address != "local":
        if address != "auto":
            check_reachable(address)
        check_joinable(address)
    try:
        init_ray(ray, address=address, include_dashboard=False, log_to_driver=True, logging_level=logging.WARNING)
    except Exception as err:  # no cluster at 'auto', a cluster of another Ray version, a local Ray that fails
        what = f"--ray-address {address}: Ray could not join the cluster" if address else "--ray: Ray could not start"
        raise ConfigError(f"{what} ({type(err).__name__}: {first_line(err)})") from None


def check_fits(gpus: float, cpus: float, nodes: list[dict]) -> None:
    """ConfigError, one line, for cells that ask for more GPUs or CPUs than any live node of the cluster has
    (`nodes`: `ray.nodes()`): Ray would keep them waiting forever."""
    alive = [node.get("Resources", {}) for node in nodes if node.get("Alive", True)]
    for asked, resource, option in ((gpus, "GPU", "--gpus-per-cell"), (cpus, "CPU", "--cpus-per-cell")):
        most = max((float(r.get(resource, 0)) for r in alive), default=0.0)
        if asked > most:
            has = f"has no {resource}s" if most == 0 else f"has {most:g} {resource}(s) at most on one node"
            rest = " (leave --gpus-per-cell out, or 0, to train the cells on CPUs)" if resource == "GPU" else ""
            raise ConfigError(f"{option} {asked:g}: the Ray cluster {has}; its cells would wait forever{rest}")


def cell_gpus(asked: float | None, nodes: list[dict]) -> float:
    """GPUs per cell: `asked` (--gpus-per-cell), else 1 where a live node of the cluster (`ray.nodes()`) has GPUs,
    0 where none has (the cells train on CPUs)."""
    if asked is not None:
        return asked
    return 1.0 if any(node.get("Resources", {}).get("GPU", 0) for node in nodes if node.get("Alive", True)) else 0.0


@contextlib.contextmanager
def holding(out: str, lock: str | None = None) -> Iterator[None]:
    """Hold the grid's `--out` for the block through its lock file (`lock`, by default `GRID_LOCK` in the folder
    `out`): ConfigError, one line, while another grid holds it (or when the file cannot be made)."""
    lock = lock or os.path.join(out, GRID_LOCK)

    def in_use(holder: str) -> ConfigError:
        return ConfigError(f"--out {out}: another grid trains into it ({holder}); wait until it ends or give another "
                           "--out")

    try:
        os.makedirs(os.path.dirname(lock) or ".", exist_ok=True)
        fd = rundir.lock_file(lock, in_use)
    except OSError as err:
        raise ConfigError(f"--out {out}: cannot create the grid's lock file {lock} ({err.strerror or err})") from None
    try:
        yield
    finally:
        rundir.unlock_file(lock, fd)


def run_cells(cells: Sequence[Cell], work: Callable[[Any], tuple[int, str | None]], args: argparse.Namespace,
              out: str, lock: str | None = None) -> int:
    """Train every cell as a Ray task (`run_cell`: `work(cell.payload)` in a worker, returning its exit code and
    why it failed), holding the grid's `out` (`holding`, through `lock`), printing a progress table every
    `args.progress_every` seconds and a line as each cell ends; the grid's exit code (the module docstring). Starts
    a local Ray (`start_ray`), or joins `args.ray_address`, unless Ray is running in this process already (then it
    is left running). ConfigError, one line, for a grid refused before its cells start."""
    check_options(args)
    with holding(out, lock):
        ray = import_ray(local=not args.ray_address)
        started = not ray.is_initialized()
        if started:
            start_ray(ray, args.ray_address)
        try:
            nodes = ray.nodes()
            gpus = cell_gpus(args.gpus_per_cell, nodes)
            check_fits(gpus, args.cpus_per_cell, nodes)
            return _drive(ray, cells, work, args, gpus)
        finally:
            if started:
                ray.shutdown()


def _drive(ray, cells: Sequence[Cell], work: Callable[[Any], tuple[int, str | None]], args: argparse.Namespace,
           gpus: float) -> int:
    """`run_cells` on a running Ray, each cell taking `gpus` GPUs."""
    print(f"Ray: each of {len(cells)} cell(s) takes {gpus:g} GPU(s) and {args.cpus_per_cell:g} CPU(s)", flush=True)
    task = ray.remote(
        num_gpus=gpus, num_cpus=args.cpus_per_cell, max_retries=args.retries, retry_exceptions=False, max_calls=1,
        runtime_env={"env_vars": worker_env(gpus)},
    )(run_cell)
    refs: dict[str, Any] = {}
    for cell in cells:  # a cell's `after` are earlier cells of the grid (others are not trained by this command)
        refs[cell.name] = task.remote(work, cell.payload, *(refs[a] for a in cell.after if a in refs))
    names = {ref: name for name, ref in refs.items()}
    after = {c.name: [a for a in c.after if a in refs] for c in cells}
    start = {c.name: c.progress() for c in cells}
    states = dict.fromkeys(refs, "queued or training")
    codes: dict[str, int] = {}
    why: dict[str, str] = {}
    seconds: dict[str, float] = {}
    began = shown = time.time()
    pending = list(refs.values())
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1,
                                      timeout=max(shown + args.progress_every - time.time(), 0))
            for ref in ready:
                name = names[ref]
                codes[name], states[name], took, reason = _result(ray, ref, args.retries)
                upstream = [a for a in after[name] if codes.get(a)]
                if codes[name] and upstream:  # Ray fails a task whose input failed without running it
                    codes[name], states[name] = codes[upstream[0]], "not run"
                    reason = f"it starts after {upstream[0]}, which failed"
                if took:
                    seconds[name] = took
                if codes[name]:
                    why[name] = reason or ""
                    print(f"error: {name}: {states[name]}" + (f": {strip_error(reason)}" if reason else ""),
                          file=sys.stderr, flush=True)
                else:
                    print(f"{name}: {states[name]}" + (f" in {took:.0f} s" if took else ""), flush=True)
            if not pending or time.time() >= shown + args.progress_every:
                shown = time.time()
                done = {c.name: c.progress() for c in cells}
                print(progress_table(cells, done, states, shown - began, start), flush=True)
    except KeyboardInterrupt:
        return _stop(ray, pending)
    print(efficiency_line(seconds, time.time() - began), flush=True)
    failed = [c.name for c in cells if codes[c.name]]
    if failed:
        listed = ", ".join(f"{name} ({states[name]})" for name in failed)
        print(f"error: {len(failed)} of {len(cells)} cell(s) failed: {listed}; the others ended", file=sys.stderr,
              flush=True)
    return codes[failed[0]] if failed else 0


def strip_error(line: str) -> str:
    """A cell's one line without its leading "error: " (the grid's own line says it)."""
    return line.removeprefix("error: ")


def _result(ray, ref, retries: int) -> tuple[int, str, float, str | None]:
    """(exit code, state, seconds its last attempt took, why it failed) of a cell's ended task: its own, or
    `EXIT_LOST` (and 0 seconds) when its worker died once more than `retries` allow."""
    try:
        code, took, why = ray.get(ref)
    except ray.exceptions.RayError as err:
        why = (f"its worker died {retries + 1} time(s) ({first_line(err)}); run the command again to resume it from "
               "its latest checkpoint")
        return EXIT_LOST, f"lost (exit {EXIT_LOST})", 0.0, why
    return code, "done" if code == 0 else f"failed (exit {code})", took, why


def _stop(ray, pending: list) -> int:
    """Ctrl-C: cancel the cells still `pending` (a running cell's worker takes it as SIGINT: it saves a checkpoint
    after its epoch in flight and ends; a queued one never starts), wait for them, `EXIT_SIGINT`. A second Ctrl-C
    stops them at once, their latest checkpoints kept."""
    print("SIGINT: stopping the cells, each after a checkpoint of its epoch in flight (Ctrl-C again stops them at "
          "once)", file=sys.stderr, flush=True)
    for ref in pending:
        ray.cancel(ref)
    try:
        if pending:
            ray.wait(pending, num_returns=len(pending))
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref, force=True)
    print("interrupted: the cells are stopped, each at its latest checkpoint; run the same command again to resume "
          "them", file=sys.stderr, flush=True)
    return EXIT_SIGINT
