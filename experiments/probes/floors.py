"""Each task's floor: the success of a policy that does nothing, over all goals and per goal subset.

    python -m experiments.probes.floors [--tasks planar_reach,...] [--resets N] [--rollouts M] [--seed 0]
        [--out results/floors]

Estimates every task's floor with `envs_mjx.floors.floor` (N resets and M episodes of the idle action, without
rendering; its docstring gives the estimator, what "does nothing" means per task and the analytic values) and
writes OUT/figures.json: one section of docs/results.md (`experiments.paper.results_docs`) with the command, the
machine, the date and commit, and the floors with their 95 % Monte Carlo half-widths under "floors" (task ->
subset -> value, half_width, resets, rollouts), which docs/results.md's table, the other tables and claims read
(`experiments.report.load_floors`) to show each score beside its floor. By default M is large for the reaching
tasks (cheap: their arms droop under the idle action, so rollouts carry the estimate) and 512 for the NICOL
tasks (whose episodes are costly; their cube rests where it starts, so the resets carry it).

Exit codes: 0 written; 2 a bad option (one `error: ...` line, nothing written); 4 the write failed; 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
from typing import Sequence

import jax

import envs_mjx
from bidal_jax.config import ConfigError
from bidal_jax.run import loop, rundir, runfiles
from envs_mjx import floors
from experiments import cli, report
from experiments.paper import protocol

PROG = "python -m experiments.probes.floors"
RESETS = 200_000
# idle episodes: NICOL's 2,048 hold each goal subset's half-width within 0.005 (about 1,000 episodes a subset)
ROLLOUTS = {"planar_reach": 50_000, "ur5_reach": 50_000, "nicol_slide": 2_048, "nicol_lift": 2_048}


def section(found: dict[str, dict[str, floors.Floor]], command: str, at: str) -> dict:
    """The figures.json section of the floors `found` (task -> subset -> `Floor`), computed at commit `at`."""
    return {
        "part": "Learning (paper Fig. 4)",
        "title": "Floors: what a policy that does nothing scores",
        "about": "Each task's floor: the success at the episode's last step of a policy that does nothing (increments "
                 "0; NICOL's absolute finger and thumb commands held open, as reset sets them), from the task's own "
                 "start and goal distributions, over all goals and per goal subset (nicol_lift's air and table "
                 "goals). Estimate: the success of N reset states plus the mean change of success over M idle "
                 "episodes (`envs_mjx/floors.py`), ± its 95 % Monte Carlo half-width. Analytic values where the "
                 "object rests where it starts: nicol_slide 0.0314; nicol_lift 0.103 over all goals, 0.196 table, "
                 "0.0102 air. The tables show each score beside its task's floor.",
        "command": command,
        "machine": f"{loop.hardware()}, {os.cpu_count()} CPU cores, JAX {jax.__version__}, without rendering",
        "date": datetime.date.today().isoformat(),
        "commit": at,
        "table": "floors",  # docs/results.md's table, from "floors" below (`results_docs.floors_table`)
        "runs": "floors",
        "floors": {task: {name: f.as_dict() for name, f in subsets.items()} for task, subsets in found.items()},
    }


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--tasks", default=",".join(protocol.paper_tasks()), help="comma list of tasks")
    parser.add_argument("--resets", type=int, default=RESETS, help="reset states per task")
    parser.add_argument("--rollouts", type=int, default=None, help="idle episodes per task (default: "
                        + ", ".join(f"{t} {n:,}" for t, n in ROLLOUTS.items()) + ")")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=os.path.join("results", "floors"))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        tasks = cli.parse_names(args.tasks, "--tasks", "task", protocol.paper_tasks())
        for name in ("resets", "rollouts"):
            if getattr(args, name) is not None and getattr(args, name) < 2:
                raise ConfigError(f"--{name} {getattr(args, name)}: must be at least 2")
        runfiles.check_output_dir(os.path.dirname(os.path.normpath(args.out)), "--out")  # its parent: before the work
    except ValueError as err:
        return cli.exit_code(err)
    key, at = jax.random.key(args.seed), report.checkout_commit()  # the code as it was when the estimate began
    found = {}
    for i, task in enumerate(tasks):
        found[task] = floors.floor(envs_mjx.make(task, render=False), jax.random.fold_in(key, i),
                                   args.rollouts or ROLLOUTS[task], args.resets)
        print(task, ", ".join(f"{name} {f.value:.4f} ± {f.half_width:.4f}" for name, f in found[task].items()),
              flush=True)
    options = [f"--tasks {args.tasks}"] * (tasks != protocol.paper_tasks()) + [f"--resets {args.resets}"] * (
        args.resets != RESETS) + [f"--rollouts {args.rollouts}"] * (args.rollouts is not None)
    options += [f"--seed {args.seed}"] * (args.seed != 0) + [f"--out {args.out}"]
    path = os.path.join(args.out, report.FLOORS_FILE)
    with rundir.writing(path):
        os.makedirs(args.out, exist_ok=True)
        runfiles.write_atomic(path, json.dumps([section(found, " ".join([PROG, *options]), at)], indent=2,
                                               ensure_ascii=False) + "\n")
    print(f"written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
