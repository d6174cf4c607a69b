"""Cells of a grid scheduled through Ray (`--ray`): the paper's experiments and `experiments.bench.sweep`.

A cell is one unit of a grid (a paper experiment's run, a sweep's variant) that a Ray task trains on its share of
a machine: `--gpus-per-cell` GPUs (1 by default; a fraction, e.g. 0.5, lets cells small enough share one GPU) and
`--cpus-per-cell` CPUs. Ray starts a local instance on this machine unless `--ray-address` names a running cluster
(`ray start --head` prints its address); `ray.init` run by the caller beforehand is used as it is.

- Results: a cell writes where the experiment's `--out` says, as it does without Ray (a run folder: config.json,
  metrics.csv, checkpoints); on a cluster `--out` is a path that every node sees.
- A worker that dies (a node lost, the process killed) has its cell retried, up to `--retries` times: a run folder
  resumes from its own latest checkpoint with its replay buffer, as running the experiment again does.
- Progress: every `--progress-every` seconds a table of the cells with their epochs done (each cell's metrics.csv
  through `report.load_run`, or the `progress` its caller reads) and an ETA, the grid's from its pace so far. As
  each cell ends, the seconds it took in its worker; at the end, the grid's wall time against their sum.
- Each worker process trains one cell and exits (`max_calls=1`), so that the GPU Ray gives it is the one its JAX
  sees and its memory goes back when the cell ends; a cell given a fraction of a GPU lets JAX take that fraction
  of the GPU's memory (`XLA_PYTHON_CLIENT_MEM_FRACTION`, where its default takes 75 %). Workers import this
  checkout's packages (`PYTHONPATH`); on a cluster every node has the project installed (`pip install -e
  ".[cluster]"`), or reads it from the shared path.

Ray is an extra: `pip install -e ".[cluster]"`; without it `--ray` is refused with one `error:` line. Exit code of
a grid: the first failing cell's in the grid's order (`experiments.cli.exit_code`), `EXIT_LOST` when a cell's
worker died more than `--retries` times, else 0; unlike the sequential path, a failing cell does not stop the others.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from typing import Any, Callable, Sequence

import experiments
from bidal_jax.config import ConfigError
from experiments import report

EXIT_LOST = 5  # a cell's worker died more often than --retries allows
EXIT_SIGINT = 130  # the driver stopped by Ctrl-C, as experiments.run's
# the share of a GPU's memory JAX may take per share of the GPU a cell is given (the rest: CUDA contexts)
MEMORY_PER_SHARE = 0.9
# the folder holding the packages, which workers put first on their path (this checkout's code, not another)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(experiments.__file__)))


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
    group.add_argument("--gpus-per-cell", type=float, default=1.0,
                       help="GPUs each cell takes: 1, or a fraction (0.5: two cells share a GPU), or 0 on machines "
                       "without GPUs (default: 1)")
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
    if not (gpus >= 0 and (gpus <= 1 or float(gpus).is_integer())):
        raise ConfigError(f"--gpus-per-cell {gpus:g}: must be 0, a fraction of one GPU or a whole number")
    if not args.cpus_per_cell >= 0:
        raise ConfigError(f"--cpus-per-cell {args.cpus_per_cell:g}: must be at least 0")
    if args.retries < 0:
        raise ConfigError(f"--retries {args.retries}: must be at least 0")
    if not args.progress_every > 0:
        raise ConfigError(f"--progress-every {args.progress_every:g}: must be positive")


def prepare_driver(args: argparse.Namespace) -> None:
    """Before anything touches a device: with Ray asked for, check its options (`check_options`) and keep this
    process's JAX on the CPU (it only builds envs for the plan; the GPUs are the cells'); without, nothing."""
    if wanted(args):
        check_options(args)
        import jax

        jax.config.update("jax_platforms", "cpu")


def epochs_done(run_dir: str) -> int:
    """The last epoch of a run folder's metrics.csv (`report.load_run`); 0 while it has none."""
    try:
        return int(report.load_run(run_dir)["epoch"][-1])
    except report.RunError:
        return 0


def worker_env(gpus_per_cell: float) -> dict[str, str]:
    """The environment variables of a cell's worker: this checkout's packages first on its path, and with a
    fraction of a GPU, JAX's share of the GPU's memory."""
    env = {"PYTHONPATH": os.pathsep.join(p for p in (ROOT, os.environ.get("PYTHONPATH")) if p)}
    if 0 < gpus_per_cell < 1:
        env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{MEMORY_PER_SHARE * gpus_per_cell:.2f}"
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


def run_cell(work: Callable[[Any], int], payload: Any, *upstream: tuple[int, float]) -> tuple[int, float]:
    """A cell's task: (`work(payload)`'s exit code, the seconds it took in the worker), or, without running it,
    (the first nonzero code of the cells it comes `after`, 0.0) (`upstream`: their results)."""
    failed = next((code for code, _ in upstream if code), 0)
    if failed:
        return failed, 0.0
    began = time.perf_counter()
    code = work(payload)
    return code, time.perf_counter() - began


def efficiency_line(seconds: dict[str, float], wall: float) -> str:
    """The grid's wall time against the sum of its cells' own times (what running them one after another in
    one process would about take): how much running them at once saved."""
    total = sum(seconds.values())
    ratio = f"{wall / total:.2f}×" if total > 0 else "—"
    return (f"grid: {wall:.0f} s of wall time for {len(seconds)} cell(s) taking {total:.0f} s together "
            f"(wall / sum: {ratio})")


def import_ray():
    """The `ray` module; ConfigError when the extra is not installed."""
    try:
        import ray
    except ImportError:
        raise ConfigError("--ray needs Ray: pip install -e \".[cluster]\"") from None
    return ray


def run_cells(cells: Sequence[Cell], work: Callable[[Any], int], args: argparse.Namespace) -> int:
    """Train every cell as a Ray task (`run_cell`: `work(cell.payload)` in a worker, returning its exit code),
    printing a progress table every `args.progress_every` seconds and a line as each cell ends; the grid's exit
    code (the module docstring; 130 when Ctrl-C stops the driver, whose tasks end with it). Starts a local Ray,
    or joins `args.ray_address`, unless Ray is running in this process already (then it is left running)."""
    check_options(args)
    ray = import_ray()
    started = not ray.is_initialized()
    if started:
        ray.init(address=args.ray_address, include_dashboard=False, log_to_driver=True)
    try:
        return _drive(ray, cells, work, args)
    except KeyboardInterrupt:  # the driver's tasks end with it; their cells continue from their checkpoints
        print("interrupted: the cells' tasks are stopped; run the same command again to resume each from its "
              "latest checkpoint", file=sys.stderr)
        return EXIT_SIGINT
    finally:
        if started:
            ray.shutdown()


def _drive(ray, cells: Sequence[Cell], work: Callable[[Any], int], args: argparse.Namespace) -> int:
    task = ray.remote(
        num_gpus=args.gpus_per_cell, num_cpus=args.cpus_per_cell, max_retries=args.retries, retry_exceptions=False,
        max_calls=1, runtime_env={"env_vars": worker_env(args.gpus_per_cell)},
    )(run_cell)
    refs: dict[str, Any] = {}
    for cell in cells:  # a cell's `after` are earlier cells of the grid (others are not trained by this command)
        refs[cell.name] = task.remote(work, cell.payload, *(refs[a] for a in cell.after if a in refs))
    names = {ref: name for name, ref in refs.items()}
    start = {c.name: c.progress() for c in cells}
    states = dict.fromkeys(refs, "queued or training")
    codes: dict[str, int] = {}
    seconds: dict[str, float] = {}
    began = shown = time.time()
    pending = list(refs.values())
    while pending:
        ready, pending = ray.wait(pending, num_returns=1, timeout=max(shown + args.progress_every - time.time(), 0))
        for ref in ready:
            name = names[ref]
            codes[name], states[name], took = _result(ray, ref, args.retries)
            if took:
                seconds[name] = took
            print(f"{name}: {states[name]}" + (f" in {took:.0f} s" if took else ""), flush=True)
        if not pending or time.time() >= shown + args.progress_every:
            shown = time.time()
            done = {c.name: c.progress() for c in cells}
            print(progress_table(cells, done, states, shown - began, start), flush=True)
    print(efficiency_line(seconds, time.time() - began), flush=True)
    return next((codes[c.name] for c in cells if codes[c.name]), 0)


def _result(ray, ref, retries: int) -> tuple[int, str, float]:
    """(exit code, state, seconds its last attempt took) of a cell's ended task: its code, or `EXIT_LOST` (and 0
    seconds) when its worker died once more than `retries` allow (one `error:` line)."""
    try:
        code, took = ray.get(ref)
    except ray.exceptions.RayError as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f"error: a cell's worker died {retries + 1} time(s) ({first}); run the command again to resume it "
              "from its latest checkpoint", file=sys.stderr)
        return EXIT_LOST, f"lost (exit {EXIT_LOST})", 0.0
    return code, "done" if code == 0 else f"failed (exit {code})", took
