"""The λ sweep: the weight of BidAL's intrinsic reward (paper Eq. 4), which the paper leaves open, chosen as
its authors would, by the learning speed of the BidAL agent.

    python -m experiments.paper.lambda_sweep [--lambdas 0,0.1,0.3,1] [--out results/lambda]
        [--dry-run | --report] [any learner or network option of experiments.run]

multimodal_bidal at each λ on nicol_slide and nicol_lift (its held-start protocol), each a run of its task's
preset in OUT/<task>/lambda-<λ> with `SEEDS` seeds and `EPOCHS` epochs: past where the curves level off, so that
the area under them measures how fast each λ learns. nicol_lift takes 5 seeds, so that the winner's run is also a
5-seed run of the lifting protocol. The runs train one after another, resumable, or with `--ray` at once
(`experiments/paper/grid.py`); `--dry-run` prints the plan with its estimated time.

Then, from whatever runs have epochs, it writes OUT/table.md: per task and λ the AUC (each seed's mean eval
success over the epochs; on nicol_lift also over air goals alone) with its 95 % Student-t interval over seeds,
and per λ the mean AUC over the tasks. The default of `TrainConfig.intrinsic_lambda` is the λ of the largest
mean (docs/deviations.md). `--report` trains nothing and writes only the table.

Exit codes as experiments.paper.curves.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any, Sequence

import numpy as np

from bidal_jax.config import ConfigError, TrainConfig
from experiments import cli, cluster, report, stats
from experiments.paper import grid
from experiments.paper.grid import Arm

PROG = "python -m experiments.paper.lambda_sweep"
AGENT = "multimodal_bidal"
EPOCHS = {"nicol_slide": 15, "nicol_lift": 20}  # multimodal_bidal levels off by epoch 10-13 and 11-16
SEEDS = {"nicol_slide": 3, "nicol_lift": 5}
LAMBDAS = (0.0, 0.1, 0.3, 1.0)


def build_parser() -> argparse.ArgumentParser:
    parser = grid.experiment_parser(PROG, __doc__, "every run")
    parser.add_argument("--lambdas", default=",".join(f"{v:g}" for v in LAMBDAS), help="comma list of λ")
    parser.add_argument("--out", default=os.path.join("results", "lambda"), help="output folder")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--dry-run", action="store_true", help="print the plan and its estimated time; write nothing")
    mode.add_argument("--report", action="store_true", help="train nothing: write table.md from the run folders")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def parse_lambdas(text: str) -> tuple[float, ...]:
    """The λ of --lambdas; ConfigError for one that is not a number ≥ 0."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = (-1.0,)
    if not values or min(values) < 0:
        raise ConfigError(f"--lambdas {text}: must be a comma list of numbers >= 0, e.g. 0,0.1,0.3,1")
    return values


def run_dir(out: str, task: str, lam: float) -> str:
    return os.path.join(out, task, f"lambda-{lam:g}")


def make_arms(lambdas: Sequence[float], extra: dict[str, Any], out: str) -> list[Arm]:
    """One run per task and λ."""
    return [Arm(f"{task}/lambda-{lam:g}", {"env": task, "agent": AGENT, "seeds": SEEDS[task], **extra,
                                            "intrinsic_lambda": lam, "epochs": EPOCHS[task],
                                            "run_dir": run_dir(out, task, lam)})
            for task in EPOCHS for lam in lambdas]


def auc_cell(success: np.ndarray) -> tuple[str, float]:
    """("mean [low, high]", mean) of the seeds' AUC: each seed's mean success over the epochs [E, S]."""
    mean, low, high = stats.rate_interval(success.mean(axis=0))
    return f"{mean:.3f} {stats.interval_text(low, high)}", mean


def table(lambdas: Sequence[float], runs: dict[tuple[str, float], dict]) -> str | None:
    """Markdown: one row per λ, a column per task (and nicol_lift's air goals), the mean over the tasks; then the
    λ of the largest mean. None when no run has epochs."""
    if not runs:
        return None
    head, rows, means = ["λ"], [], {}
    head += [f"{task} AUC ({SEEDS[task]} seeds, {EPOCHS[task]} epochs)" for task in EPOCHS]
    head += ["nicol_lift AUC over air goals", "mean AUC over the tasks"]
    for lam in lambdas:
        cells, values = [f"{lam:g}"], []
        for task in EPOCHS:
            run = runs.get((task, lam))
            text, mean = auc_cell(run["success"]) if run else ("—", np.nan)
            cells.append(text)
            values.append(mean)
        air = runs.get(("nicol_lift", lam), {}).get("success_air")
        cells.append("—" if air is None else auc_cell(air)[0])
        means[lam] = float(np.mean(values))
        cells.append("—" if np.isnan(means[lam]) else f"{means[lam]:.3f}")
        rows.append(cells)
    found = {lam: m for lam, m in means.items() if not np.isnan(m)}
    best = f"Largest mean AUC over the tasks: λ = {max(found, key=found.get):g}" if found else "No λ has every task"
    default = TrainConfig().intrinsic_lambda
    return "\n".join([
        f"# The λ sweep: {AGENT}, AUC with its 95 % Student-t interval over seeds", "",
        report.markdown_table(head, rows), "",
        f"{best}; the default (`TrainConfig.intrinsic_lambda`) is {default:g}.", "",
        f"Regenerate from the run folders: `{PROG} --report`", "",
    ])


def main(argv: Sequence[str] | None = None) -> int:
    args, rest = build_parser().parse_known_args(argv)
    try:
        lambdas = parse_lambdas(args.lambdas)
        arms = grid.checked_arms(make_arms(lambdas, grid.pass_through(rest, PROG), args.out))
        cluster.prepare_driver(args)
    except ConfigError as err:
        return cli.exit_code(err)
    try:
        if not args.report:
            envs = grid.make_envs(arms)
            print(grid.estimated_plan(arms, envs), flush=True)
            if args.dry_run:
                print(grid.DRY_RUN)
                return 0
            code = grid.train_arms(arms, envs, args, args.out)
            if code:  # a refusal or a failed run ends the command on its error line (`--report` writes the table)
                return code
        runs = {(arm.given["env"], arm.given["intrinsic_lambda"]): run for arm in arms
                if (run := grid.loaded(arm.run_dir))}
        grid.write_table(args.out, table(lambdas, runs))
    except cli.FAILURES as err:
        return cli.exit_code(err)
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
