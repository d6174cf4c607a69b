"""Learning curves of training runs: evaluation success against env steps, mean ± std over seeds.

    python -m experiments.plot runs/a runs/b [--out curves.png] [--x env_steps|epoch|wall_time]
        [--label-by agent|run|env|GROUP.FIELD] [--label runs/b=transfer] [--panel-by env|GROUP.FIELD]
        [--last-n 10] [--threshold 0.5]

The paper's learning curves (Fig. 4), noise runs (Fig. 5, Table II) and transfer arms (Fig. 6)
are all this plot: one panel per env (or per `--panel-by` value, e.g. the noise level κ), one
line per label, the seed mean of `eval_success` with a shaded band of ± one standard deviation
over seeds. It reads each run directory's `config.json` and `metrics.csv` (experiments/run.py),
writes the figure FILE.png (`--out`; a name without .png gets it) and beside it FILE.csv (the
plotted numbers: panel, label, x, mean, std, n_seeds), and prints the summary table (final
success over the last N epochs) as Markdown; the work is `experiments/report.py`'s.

Labels are agent names unless runs of one panel share an agent; those are labelled by their
directory's basename. `--label RUN_DIR=NAME` names a run outright (the transfer arms
"scratch" and "transfer"); `--label-by train.intrinsic_lambda` labels by a config value.

Exit codes: 0 done; 2 a run directory without config.json or metrics.csv, or with a damaged one (the line names
the file), a bad option, or an --out folder that does not exist or cannot be written (refused before anything is
read); 4 writing FILE.png or FILE.csv failed (no space, quota, read-only file system, permission denied);
130 stopped by Ctrl-C. Each failure is one `error: ...` line on stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Sequence

from bidal_jax.run import rundir, runfiles
from experiments import cli
from experiments.report import X_AXES, curves, load_run, plot, summary_table


def _label_option(text: str) -> tuple[str, str]:
    run_dir, sep, name = text.rpartition("=")
    if not sep or not run_dir or not name:
        raise argparse.ArgumentTypeError(f"{text!r}: expected RUN_DIR=NAME")
    return run_dir, name


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m experiments.plot",
        description="Plot eval success of runs (mean ± std over seeds), one panel per env; write FILE.png/.csv.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("run_dirs", nargs="+", metavar="RUN_DIR", help="run directories (config.json + metrics.csv)")
    parser.add_argument("--out", default="learning_curves.png", metavar="FILE.png",
                        help="the figure (.png added if missing); its numbers go beside it, FILE.csv")
    parser.add_argument("--x", default="env_steps", choices=list(X_AXES), help="x axis")
    parser.add_argument(
        "--label-by",
        default="agent",
        help="label lines by agent, run (directory basename), env or a config GROUP.FIELD",
    )
    parser.add_argument("--panel-by", default="env", help="one panel per value of this (keys as --label-by)")
    parser.add_argument(
        "--label",
        action="append",
        type=_label_option,
        default=[],
        metavar="RUN_DIR=NAME",
        help="name a run's line (repeatable); overrides --label-by",
    )
    parser.add_argument("--last-n", type=int, default=10, help="epochs averaged for the printed final success")
    parser.add_argument("--threshold", type=float, help="also print when each mean curve first reaches this")
    parser.add_argument("--title", default="", help="figure title")
    parser.add_argument("--air-goals", action="store_true", help="plot and print the success over air goals alone "
                        "(nicol_lift's lifting skill, metrics.csv's eval_success_air)")
    return parser


def air_goals(run: dict) -> dict:
    """The run with its success over air goals as its success; ValueError for a run without them."""
    if run["success_air"] is None:
        raise ValueError(f"{run['dir']}: --air-goals: its metrics.csv has no success over air goals")
    return {**run, "success": run["success_air"]}


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.last_n < 1:
            raise ValueError(f"--last-n {args.last_n}: must be a positive integer")
        runfiles.check_output_dir(os.path.dirname(args.out), "--out")
        prefix = args.out.removesuffix(".png")
        runs = [air_goals(load_run(d)) if args.air_goals else load_run(d) for d in args.run_dirs]
        labels = dict(args.label)
        cs = curves(runs, args.label_by, labels, args.panel_by)
        with rundir.writing(f"{prefix}.png and {prefix}.csv"):
            png, table = plot(cs, prefix, args.x, args.title)
        summary = summary_table(runs, args.last_n, args.label_by, labels, args.threshold, args.panel_by)
    except (ValueError, rundir.DiskError) as err:
        return cli.exit_code(err)
    print(f"wrote {png} and {table}\n\n{summary}")
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
