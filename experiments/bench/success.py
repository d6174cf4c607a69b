"""Time to a success threshold on CPU, compilation included, optionally beside another commit.

    taskset -c 0,1 python -m experiments.bench.success --ref 4fd28b3
    python -m experiments.bench.success --cases planar --target 0.5 --repeats 3 --out success.json

Cases, each `python -m experiments.run ... --target-success T` (which stops the run at the first
epoch whose mean eval success over seeds is ≥ T):

- planar: `--env planar_reach --agent proprio_baseline --seeds 3` (its preset: 40 epochs)
- main: `--env ur5_reach`, the main command (multimodal_bidal, its preset: 15 epochs)

Each repeat of a case runs it twice as a subprocess with `--quiet` in a new run directory: cold,
with a fresh, empty JAX persistent compilation cache, then warm, the same command with that cache
now filled. The figures of a case are medians over its runs:

- compile (cold cache, warm cache): the run's stderr line "compiled in X s": building the initial
  state (init compiled and run) and tracing and compiling the epoch program, from a cache when
  warm (the cache skips XLA's compile, not tracing the program). The run sets the cache's
  minimum compile time to 1 s, so smaller programs compile in every run, as in any run.
- training: metrics.csv's `wall_time` at the first epoch whose mean eval success is ≥ T. The
  run starts that clock after compiling, so it holds the epochs and, between them, the metrics,
  the divergence check and the checkpoints saved before that epoch. Commits before d807503
  compile the epoch program in the first epoch and print no "compiled in" line: there, compile
  is the first epoch's duration minus the median duration of the later ones (none with one
  epoch), and training is `wall_time` minus it (the table's row "compile from" says which).
- total (cold cache, warm cache): the subprocess from start to exit: Python and JAX start-up,
  the run's checks, compile, training and the checkpoint saved at the threshold epoch, where
  the run stops.
- epochs, env steps per seed and gradient updates per seed (epochs × cycles_per_epoch ×
  updates_per_cycle of the run's config.json) at that epoch, and whether it was reached: a run
  that never reaches T in its epochs has no training or total time.

`--ref GIT_REF` runs the same cases at another commit, from a detached `git worktree` of it in
a temporary directory (removed afterwards, also on an error or Ctrl-C), with caches of its own;
each repeat of a case runs there, then here, so that both see the same machine. The table then
has the columns this commit, ref and this ÷ ref. `--epochs N` caps every run (smoke runs).

Every run imports the code of its checkout (working directory and PYTHONPATH), whatever is
installed: its `assets/` is registered as the package `envs_mjx.assets` (an editable install of
another checkout would serve that one's), and a run that imported a module of the project from
elsewhere fails. Every run gets the environment this command was started with
(`experiments.CALLER_ENVIRONMENT`) and sets its own flags. Each run's compilation cache is given
as `$BIDAL_JAX_CACHE` (the run's own setting) and `$JAX_COMPILATION_CACHE_DIR`.

Exit codes: 0 done (threshold reached or not); 1 a run failed (one `error: ...` line with its
last line of stderr); 2 a bad option (one `error: ...` line, nothing run); 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import json
import os
import platform
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

import experiments
from experiments.report import curves, load_run, markdown_table, time_to_threshold

PROG = "python -m experiments.bench.success"
CASES = {
    "planar": ("--env", "planar_reach", "--agent", "proprio_baseline", "--seeds", "3"),
    "main": ("--env", "ur5_reach"),
}
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
COMPILED = re.compile(r"^compiled in ([0-9.]+) s$", re.MULTILINE)
# experiments.run of the checkout in the working directory (see the module docstring)
LAUNCHER = """\
import importlib.util, os, sys
tree = os.path.join(os.path.realpath(os.getcwd()), "")
assets = os.path.join(tree, "assets", "__init__.py")
if os.path.isfile(assets):
    spec = importlib.util.spec_from_file_location("envs_mjx.assets", assets,
                                                  submodule_search_locations=[os.path.dirname(assets)])
    sys.modules[spec.name] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sys.modules[spec.name])
from experiments import run
code = run.main(sys.argv[1:])
stray = sorted(m.__file__ for name, m in list(sys.modules.items())
               if name.partition(".")[0] in ("bidal_jax", "envs_mjx", "experiments")
               and getattr(m, "__file__", None) and not os.path.realpath(m.__file__).startswith(tree))
if stray:
    sys.exit(f"error: imported from outside {tree}: {', '.join(stray)}")
sys.exit(code)
"""
# (key, label, the runs it is the median over: "cold", "warm" or None for all, the run figure)
ROWS = (
    ("compile_cold_s", "compile, cold cache", "cold", "compile_s"),
    ("compile_warm_s", "compile, warm cache", "warm", "compile_s"),
    ("training_s", "training to the threshold", None, "training_s"),
    ("total_cold_s", "total to the threshold, cold cache", "cold", "total_s"),
    ("total_warm_s", "total to the threshold, warm cache", "warm", "total_s"),
    ("epochs", "epochs", None, "epochs"),
    ("env_steps_per_seed", "env steps per seed", None, "env_steps_per_seed"),
    ("updates", "gradient updates per seed", None, "updates"),
)


def compile_seconds(stderr: str, wall_time: np.ndarray) -> tuple[float | None, float | None, str]:
    """(seconds compiling, the part of them inside metrics.csv's wall_time, where they come from):
    the "compiled in" line (none inside); else the first epoch's duration minus the median of
    the later epochs' (all inside; None with one epoch)."""
    logged = COMPILED.search(stderr)
    if logged:
        return float(logged.group(1)), 0.0, "log"
    durations = np.diff(wall_time, prepend=0.0)
    first = float(durations[0] - np.median(durations[1:])) if len(durations) > 1 else None
    return first, first, "first epoch"


def run_figures(run_dir: str, stderr: str, seconds: float, target: float) -> dict:
    """The figures of one finished run (module docstring) from its directory, its stderr and
    its seconds from start to exit; None where there is none."""
    run = load_run(run_dir)
    compile_s, in_wall_time, source = compile_seconds(stderr, run["wall_time"])
    figures = {"compile_s": compile_s, "compile_from": source,
               "epochs_run": int(run["epoch"][-1]), "reached": False, "training_s": None, "total_s": None,
               "epochs": None, "env_steps_per_seed": None, "updates": None}
    reached = time_to_threshold(curves([run])[0], target)
    if reached is None:
        return figures
    train = run["config"]["train"]
    return {**figures, "reached": True, "total_s": seconds, "epochs": reached.epoch,
            "training_s": None if in_wall_time is None else reached.wall_time - in_wall_time,
            "env_steps_per_seed": reached.env_steps,
            "updates": reached.epoch * train["cycles_per_epoch"] * train["updates_per_cycle"]}


def run_args(case: str, run_dir: str, target: float, epochs: int | None) -> list[str]:
    """The experiments.run options of one run of `case`."""
    cap = ["--epochs", str(epochs)] if epochs else []
    return [*CASES[case], *cap, "--run-dir", run_dir, "--quiet", "--target-success", str(target)]


def launch(tree: str, args: list[str], cache: str) -> tuple[str, float]:
    """Run experiments.run with `args` from the checkout `tree` with the persistent compilation
    cache `cache`: (its stderr, seconds from start to exit). RuntimeError if it fails."""
    env = {
        **experiments.CALLER_ENVIRONMENT,
        "PYTHONPATH": os.pathsep.join(filter(None, (tree, os.environ.get("PYTHONPATH")))),
        "BIDAL_JAX_CACHE": cache,
        # for what compiles before the run sets its cache, and commits without that setting
        "JAX_COMPILATION_CACHE_DIR": cache,
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
        "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0",
    }
    start = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", LAUNCHER, *args], cwd=tree, env=env, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if proc.returncode:
        last = (proc.stderr.strip().splitlines() or ["(no stderr)"])[-1]
        raise RuntimeError(f"experiments.run {' '.join(args)} in {tree} exited with {proc.returncode}: {last}")
    return proc.stderr, seconds


def summarize(runs: list[dict]) -> dict:
    """Per row of ROWS, the median over the runs that have the figure (None if none has it); how
    many runs reached the threshold, of how many, the most epochs a run ran, and where the
    compile figures come from ("log", "first epoch")."""
    summary = {}
    for key, _, cache, figure in ROWS:
        values = [r[figure] for r in runs if r[figure] is not None and cache in (None, r["cache"])]
        summary[key] = statistics.median(values) if values else None
    return {**summary, "reached": sum(r["reached"] for r in runs), "runs": len(runs),
            "epochs_run": max(r["epochs_run"] for r in runs),
            "compile_from": ", ".join(sorted({r["compile_from"] for r in runs}))}


def _cell(key: str, value: float | None) -> str:
    if value is None:
        return "—"
    return f"{value:.1f} s" if key.endswith("_s") else f"{value:,.0f}"


def _ratio(this: float | None, ref: float | None) -> str:
    return "—" if this is None or not ref else f"{this / ref:.2f}"


def _reached(summary: dict) -> str:
    if summary["reached"] == summary["runs"]:
        return "yes"
    if not summary["reached"]:
        return f"no ({summary['epochs_run']} epochs)"
    return f"{summary['reached']} of {summary['runs']} runs"


def table(summaries: dict[str, dict[str, dict]], commits: dict[str, str]) -> str:
    """Markdown: a row per case and quantity; a column per commit of `commits` ("this", then
    "ref" and this ÷ ref). `summaries[case][commit]` is a `summarize` result."""
    with_ref = "ref" in commits
    header = ["case", "quantity", *(f"{label} ({commit})" for label, commit in commits.items())]
    rows = []
    for case, by_commit in summaries.items():
        for key, label, *_ in ROWS:
            values = [by_commit[c][key] for c in commits]
            ratio = [_ratio(*values)] if with_ref else []
            rows.append([case, label, *(_cell(key, v) for v in values), *ratio])
        for label, cell in (("threshold reached", _reached), ("compile from", lambda s: s["compile_from"])):
            rows.append([case, label, *(cell(by_commit[c]) for c in commits), *[""] * with_ref])
    return markdown_table(header + ["this ÷ ref"] * with_ref, rows)


def _progress(case: str, label: str, commit: str, figures: dict, target: float) -> str:
    """One line for one finished run."""
    head = f"{case}, {label} {commit}, {figures['cache']} cache: compile {_cell('compile_s', figures['compile_s'])}"
    if not figures["reached"]:
        return f"{head}; eval success ≥ {target} not reached in {figures['epochs_run']} epochs"
    return (f"{head}; eval success ≥ {target} at epoch {figures['epochs']} (training "
            f"{_cell('training_s', figures['training_s'])}), total {_cell('total_s', figures['total_s'])}")


def measure(trees: dict[str, str], commits: dict[str, str], cases: list[str], args: argparse.Namespace,
            work: str) -> dict[str, dict[str, list[dict]]]:
    """Every run: {case: {commit label: [figures of each run]}}, the checkouts of `trees` (in its
    order) one after another for each repeat of each case, caches and run directories in `work`."""
    runs: dict[str, dict[str, list[dict]]] = {case: {label: [] for label in commits} for case in cases}
    for case in cases:
        for _ in range(args.repeats):
            for label, tree in trees.items():
                cache = tempfile.mkdtemp(prefix="cache-", dir=work)
                for kind in ("cold", "warm"):
                    run_dir = os.path.join(tempfile.mkdtemp(dir=work), "run")
                    stderr, seconds = launch(tree, run_args(case, run_dir, args.target, args.epochs), cache)
                    figures = {"cache": kind, **run_figures(run_dir, stderr, seconds, args.target)}
                    shutil.rmtree(os.path.dirname(run_dir))  # checkpoints can be large
                    runs[case][label].append(figures)
                    print(_progress(case, label, commits[label], figures, args.target), flush=True)
    return runs


def _git(repo: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", "-C", repo, *args], capture_output=True, text=True)


def resolve_commit(repo: str, ref: str) -> str | None:
    """The short hash of the commit `ref` names in the repository at `repo`, or None."""
    proc = _git(repo, "rev-parse", "--verify", "--quiet", "--short", f"{ref}^{{commit}}")
    return proc.stdout.strip() if proc.returncode == 0 else None


@contextlib.contextmanager
def worktree(repo: str, commit: str):
    """A detached `git worktree` of `commit` in a temporary directory, removed on exit (also on
    an error or Ctrl-C)."""
    path = tempfile.mkdtemp(prefix="bench_success-ref-")
    try:
        proc = _git(repo, "worktree", "add", "--detach", path, commit)
        if proc.returncode:
            raise RuntimeError(f"git worktree add {commit} failed: {proc.stderr.strip()}")
        yield path
    finally:
        _git(repo, "worktree", "remove", "--force", path)
        shutil.rmtree(path, ignore_errors=True)  # what remains if it was never added


def machine() -> dict:
    """The CPU, its cores, the CPUs this process may run on, Python, JAX and XLA_FLAGS."""
    with open("/proc/cpuinfo") as f:
        cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), platform.processor())
    return {"cpu": cpu, "cores": os.cpu_count(), "affinity": sorted(os.sched_getaffinity(0)),
            "python": platform.python_version(), "jax": importlib.metadata.version("jax"),
            "jaxlib": importlib.metadata.version("jaxlib"), "xla_flags": os.environ.get("XLA_FLAGS", "")}


def header(info: dict, commits: dict[str, str], cases: list[str], args: argparse.Namespace) -> str:
    """What is measured where: the machine (`machine()`), the commits and the options."""
    cpus = ",".join(map(str, info["affinity"]))
    return "\n".join([
        f"machine: {info['cpu']}, {info['cores']} cores, this process may run on CPUs {cpus}",
        f"Python {info['python']}, jax {info['jax']}, jaxlib {info['jaxlib']}, "
        f"XLA_FLAGS: {info['xla_flags'] or '(unset)'}",
        *(f"{label}: {commit}" for label, commit in commits.items()),
        f"target: mean eval success ≥ {args.target}; cases: {', '.join(cases)}; repeats: {args.repeats}"
        + (f"; at most {args.epochs} epochs" if args.epochs else ""),
        "",
    ])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of: {', '.join(CASES)}")
    parser.add_argument("--target", type=float, default=0.9, help="the mean eval success to reach, in (0, 1]")
    parser.add_argument("--repeats", type=int, default=1, help="cold and warm runs per case and commit (medians)")
    parser.add_argument("--ref", default="", help="also measure this git commit (branch, tag or hash), side by side")
    parser.add_argument("--epochs", type=int, default=None, help="cap every run at N epochs (smoke runs); "
                        "default: the cases' presets")
    parser.add_argument("--out", default="", help="also write every figure to this JSON file")
    return parser


def check_args(args: argparse.Namespace) -> list[str]:
    """The cases asked for; ValueError naming a bad option and what it allows."""
    cases = list(dict.fromkeys(args.cases.split(",")))
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        raise ValueError(f"--cases: unknown case {unknown[0]!r}; allowed: {', '.join(CASES)} (comma-separated)")
    if not 0 < args.target <= 1:
        raise ValueError(f"--target {args.target}: must be in (0, 1]")
    if args.repeats < 1:
        raise ValueError(f"--repeats {args.repeats}: must be at least 1")
    if args.epochs is not None and args.epochs < 1:
        raise ValueError(f"--epochs {args.epochs}: must be at least 1")
    if args.out and not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
        raise ValueError(f"--out {args.out}: its directory does not exist")
    return cases


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cases = check_args(args)
        commits = {"this": resolve_commit(ROOT, "HEAD") or "unknown"}
        if _git(ROOT, "status", "--porcelain").stdout.strip():
            commits["this"] += " + changes"
        if args.ref:
            commits["ref"] = resolve_commit(ROOT, args.ref)
            if commits["ref"] is None:
                raise ValueError(f"--ref {args.ref}: not a commit of the git repository at {ROOT}")
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    info = machine()
    print(header(info, commits, cases, args), flush=True)
    try:
        with contextlib.ExitStack() as stack:
            work = stack.enter_context(tempfile.TemporaryDirectory(prefix="bench_success-"))
            trees = {"ref": stack.enter_context(worktree(ROOT, commits["ref"]))} if args.ref else {}
            runs = measure({**trees, "this": ROOT}, commits, cases, args, work)
    except (RuntimeError, ValueError) as err:  # a run that failed, or whose directory cannot be read
        print(f"error: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    summaries = {case: {label: summarize(r) for label, r in by_commit.items()} for case, by_commit in runs.items()}
    print(f"\ntime to mean eval success ≥ {args.target}, medians over {args.repeats} repeat(s) of a cold and a "
          f"warm run\n\n{table(summaries, commits)}")
    if args.out:
        cases_out = {case: {label: {"summary": summaries[case][label], "runs": r} for label, r in by_commit.items()}
                     for case, by_commit in runs.items()}
        with open(args.out, "w") as f:
            json.dump({"machine": info, "commits": commits, "target": args.target, "repeats": args.repeats,
                       "epochs_cap": args.epochs, "cases": cases_out}, f, indent=2)
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
