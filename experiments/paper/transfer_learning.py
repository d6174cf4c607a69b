"""The transfer experiment (paper Sec. IV-C, Fig. 6): reduced lift learns from scratch and
from the representation of a sliding run.

    python -m experiments.paper.transfer_learning [--seeds 5] [--out results/transfer] [--source RUN_DIR]
        [--source-epochs N] [--epochs N] [--init-normaliser fresh|inherit]
        [--arms source,transfer,scratch] [--dry-run]
        [any learner or network option of experiments.run]

Three runs of multimodal BidAL, each `--seeds` seeds vmapped as one program, in `--out`:

- `source/`: nicol_slide with its preset (`--source-epochs` epochs), unless `--source RUN_DIR`
  names a finished one (`--source-checkpoint` picks a step or "best"; default the latest);
- `transfer/`: nicol_lift_reduced whose encoder and forward and inverse models (`--init-parts`)
  start from the source's (`bidal_jax/run/transfer.py`: seed i from the source's seed i, the proprio
  rows matched by segment name, optimisers fresh), its proprio normaliser fresh (zero counts), or the
  source's, rows matched alike, with `--init-normaliser inherit` (recorded in its config.json);
- `scratch/`: the same run from a fresh start: same seeds, epochs and settings.

Both arms train under HER's pick-and-place protocol, the lifting tasks' preset: half of their training
episodes start with the cube held, evaluation from reset (the paper is silent; docs/deviations.md);
`--exploration-starts 0` runs the plain protocol, a labelled variant written to results/transfer-plain by
default. Learner and network
options (e.g. `--num-envs 16 --conv-channels 4`) and `--checkpoint-every` pass to all three runs.

Then, from whatever runs have epochs, it writes `success.png` and `success.csv` (eval success
against env steps per seed, mean ± std over seeds, both arms; `experiments/report.py`) and
`table.md` (env steps and wall time to 0.3 and 0.5 success, area under the curve, final
success; for the difference transfer − scratch of AUC and of env steps to 0.3 and 0.5, per seed
and censored at the run's total env steps where a seed never gets there, Welch's 95 % t interval over
seeds, `experiments/stats.py`; the runs, source included, that
are stale, whose figures are not today's experiment; and the command that regenerates it). Each
run's metrics are its `metrics.csv`; times are its `wall_time`: seconds of training, compilation not
counted. Every training command compiles into the persistent compilation
cache (`cli.start_run`) and both arms' programs are identical, so whichever arm compiles second skips
most of it; counting compilation would favour that arm. The source's training time is not in the
transfer arm's times.

Resumable: run the same command again. A run whose latest checkpoint is at its epoch count is
skipped, an interrupted one resumes from its latest checkpoint, one without a checkpoint starts
again, and a stale one (made on other physics or with another config) is refused before any run of
`--arms` trains (`experiments/paper/grid.py`). Runs are driven in-process (`experiments/cli.py`: prepare,
then train), in the order source, transfer, scratch, so that the transfer's checks run as early
as they can; `--ray` trains them as cells of Ray tasks (`experiments/cluster.py`), source and scratch
at once, the transfer arm once its source has ended. `--arms` trains
only the named runs: `--arms source` and `--arms scratch` can run as two processes at once (the
scratch arm does not need the source), then `--arms transfer`, which refuses to start while its source is
unfinished (`refuse_unfinished_source`); any of them writes the results
of whatever runs have epochs, and `--arms none` writes only those (e.g. from run folders
whose checkpoints were deleted). `--dry-run` prints the plan, each run with its state (new, resume,
done or stale) and its estimated time (`grid.estimated_plan`), and trains and writes nothing.

Exit codes as experiments.run: 0 done; 2 bad option, config or checkpoint (one `error: ...`
line), or a run folder with a damaged file (one line naming it; the experiment stops on it); 3 diverged; 4 the
disk (a run's write, or table.md or the figure); 6 out of device memory; 130 and 143 stopped by SIGINT and SIGTERM (a
checkpoint was saved). A refusal or a failed run ends the command with its error as the last line: nothing is
plotted or tabled after it (`--arms none` writes the results of the runs that have epochs).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any, Sequence

import numpy as np

from bidal_jax.config import INIT_NORMALISERS, ConfigError, RunConfig, resolve
from bidal_jax.run import multihost
from experiments import cli, cluster, report, stats
from experiments.paper import grid
from experiments.paper.grid import Arm
from experiments.paper.protocol import AGENT, DEFAULT_SEED, SOURCE_ENV, TARGET_ENV, THRESHOLDS, seed_measures

PROG = "python -m experiments.paper.transfer_learning"
ARMS = ("source", "transfer", "scratch")


def build_parser() -> argparse.ArgumentParser:
    parser = grid.experiment_parser(PROG, __doc__, "all three runs")
    parser.add_argument("--out", default=None, help="output folder (default results/transfer, or "
                        "results/transfer-plain with --exploration-starts 0)")
    parser.add_argument("--source", default=None, metavar="RUN_DIR", help="a nicol_slide run to transfer from "
                        "instead of training OUT/source")
    parser.add_argument("--source-checkpoint", default=None, help="the source's checkpoint: a step or 'best' "
                        "(default: the latest)")
    parser.add_argument("--source-epochs", type=int, default=None, help="epochs of the source (default: its preset)")
    parser.add_argument("--epochs", type=int, default=None, help="epochs of both reduced-lift arms (default: preset)")
    parser.add_argument("--seeds", type=int, default=5, help="seeds of every run, vmapped (the source needs as many)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="first random seed of every run")
    parser.add_argument("--init-parts", default=RunConfig.init_parts, help="networks the transfer arm restores")
    parser.add_argument("--init-normaliser", default=RunConfig.init_normaliser, choices=INIT_NORMALISERS,
                        help="the transfer arm's proprio normaliser: fresh (zero counts) or inherit (the source's)")
    parser.add_argument("--arms", default=",".join(ARMS), help="the runs this command trains, a comma list of "
                        f"{', '.join(ARMS)} (default all; the others are only read for the results), so that "
                        "runs can be trained by separate processes at once; 'none' only writes the results")
    parser.add_argument("--last-n", type=int, default=10, help="epochs averaged for the final success in table.md")
    parser.add_argument("--dry-run", action="store_true", help="print the plan (each run's state: new, resume, "
                        "done or stale); train and write nothing")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def parse_arms(text: str) -> frozenset[str]:
    """The arms named by --arms ('none': no arm); ConfigError naming one that is not an arm."""
    return frozenset() if text == "none" else frozenset(cli.parse_names(text, "--arms", "arm", ARMS))


def source_dir(args: argparse.Namespace, out: str) -> str:
    return args.source or os.path.join(out, "source")


def make_arms(args: argparse.Namespace, extra: dict[str, Any], out: str) -> list[Arm]:
    """The runs to make, in training order, with every config field they set (epochs resolved)."""
    common = {"agent": AGENT, "seeds": args.seeds, "seed": args.seed, **extra}
    target = {**common, "env": TARGET_ENV}  # its preset's held starts, unless --exploration-starts 0 is passed
    source_ref = source_dir(args, out) + (f":{args.source_checkpoint}" if args.source_checkpoint else "")
    runs = [] if args.source else [("source", {**common, "env": SOURCE_ENV}, args.source_epochs)]
    runs += [
        ("transfer", {**target, "init_from": source_ref, "init_parts": args.init_parts,
                      "init_normaliser": args.init_normaliser}, args.epochs),
        ("scratch", target, args.epochs),
    ]
    arms = []
    for name, given, epochs in runs:
        given = {**given, "run_dir": os.path.join(out, name), **({"epochs": epochs} if epochs else {})}
        after = ("source",) if name == "transfer" and not args.source else ()  # under Ray: once the source ends
        arms.append(Arm(name, {**given, "epochs": resolve(given).run.epochs}, after=after))
    return arms


def refuse_unfinished_source(arms: Sequence[Arm], train_names: frozenset[str]) -> None:
    """ConfigError, one line, when the transfer arm would start (it has no checkpoint yet) from this command's own
    source run while that run is unfinished and not trained first by the same command (`--arms transfer` alone):
    it would start from a half-trained representation. A source named by --source is the user's to vouch for."""
    by_name = {arm.name: arm for arm in arms}
    if "transfer" not in train_names or "source" in train_names or "source" not in by_name:
        return
    source, transfer = by_name["source"], by_name["transfer"]
    reached = grid.latest(source) or 0
    if grid.latest(transfer) is None and reached < source.epochs:
        raise ConfigError(
            f"--arms transfer: its source {source.run_dir} is at epoch {reached} of {source.epochs}, and the transfer "
            "arm starts from its parameters. Nothing was trained: finish the source first (--arms source)"
        )


def _cell(hit: report.Reached | None) -> tuple[str, str]:
    if hit is None:
        return "not reached", "not reached"
    return f"{hit.env_steps:,.0f} (epoch {hit.epoch})", f"{hit.wall_time:,.0f} s"


def results_table(curves: Sequence[report.Curve], last_n: int) -> str:
    """Markdown, one row per arm: env steps and wall time to each threshold (first epoch whose seed
    mean reaches it), normalised AUC, final success (mean ± std over seeds of the last `last_n` epochs)."""
    head = ["arm", "seeds", "epochs", "env steps per seed"]
    for t in THRESHOLDS:
        head += [f"env steps to {t:g}", f"time to {t:g}"]
    head += ["AUC", f"final success (last {last_n} epochs)"]
    rows = []
    for c in curves:
        cells = [c.label, str(c.n_seeds), str(len(c.epoch)), f"{c.env_steps[-1]:,.0f}"]
        for t in THRESHOLDS:
            cells += _cell(report.time_to_threshold(c, t))
        rows.append(cells + [f"{report.normalized_auc(c):.3f}", report.final_cell(c, last_n)])
    return report.markdown_table(head, rows)


def _arm_cell(values: np.ndarray, censored: np.ndarray, digits: int) -> str:
    marks = f" ({censored.sum()} of {censored.size} censored*)" if censored.any() else ""
    return f"{values.mean():,.{digits}f}{marks}"


def difference_table(transfer: report.Curve, scratch: report.Curve) -> str:
    """Markdown, one row per `seed_measures` measure: each arm's mean over seeds, transfer − scratch and its
    95 % Welch t interval over seeds (`stats.welch_interval`)."""
    head = ["measure (per seed)", "transfer", "scratch", "transfer − scratch", "95 % Welch t"]
    rows = []
    for (name, (a, a_cut)), (b, b_cut) in zip(seed_measures(transfer).items(), seed_measures(scratch).values()):
        digits = 3 if name == "AUC" else 0
        diff, low, high = stats.welch_interval(a, b)
        rows.append([name, _arm_cell(a, a_cut, digits), _arm_cell(b, b_cut, digits), f"{diff:,.{digits}f}",
                     stats.interval_text(low, high, digits)])
    return report.markdown_table(head, rows)


def short_note(arms: Sequence[Arm], runs: dict[str, dict]) -> list[str]:
    """The warning above the intervals while an arm of `arms` (transfer and scratch, of one budget) has run fewer
    than its epochs (`grid.unfinished`); `runs`: name -> run."""
    if not grid.unfinished(arms, runs):
        return []
    ran = " and ".join(str(int(runs[arm.name]["epoch"][-1])) for arm in arms)
    return [
        f"**Not the experiment yet**: the arms have run {ran} of their {arms[0].epochs} epochs "
        f"({', '.join(arm.name for arm in arms)}), so the intervals below compare the epochs each has run, not the "
        "experiment's budget; they stand once both arms have finished.",
        "",
    ]


def difference_notes(transfer: report.Curve, scratch: report.Curve, warning: Sequence[str]) -> list[str]:
    """The section of table.md on the difference between the arms, `warning` (`short_note`) above the intervals."""
    return [
        "## Transfer − scratch, 95 % intervals over seeds",
        "",
        *warning,
        "Per seed: AUC is its mean success over the epochs run; env steps to a threshold are those of the first "
        "epoch whose success (that seed's) is at least it. *A seed that never reaches a threshold is censored at "
        "its run's total env steps, which understates its time. Welch's t interval of the difference of means "
        "(`experiments.stats.welch_difference`, which keeps its 95 % at 5 seeds an arm where a percentile bootstrap "
        "does not; — where it is undefined: one seed, or no spread in either arm).",
        "",
        difference_table(transfer, scratch),
        "",
    ]


def regenerate_command(args: argparse.Namespace, out: str) -> str:
    """The command that rewrites table.md, success.png and success.csv from the run folders alone."""
    options = [f"--out {out}", f"--seeds {args.seeds}" if args.seeds != 5 else "",
               f"--last-n {args.last_n}" if args.last_n != 10 else ""]
    return " ".join([PROG, "--arms none", *filter(None, options)])


def stale_note(arms: Sequence[Arm], runs: dict[str, dict], today: dict[str, str | None]) -> list[str]:
    """The line below the arms' table naming the runs of `arms` (the source's too; `runs`: arm name -> its loaded
    run) that are stale (`grid.stale_runs`, `today`: env name -> its physics fingerprint today); none when none is."""
    stale = grid.stale_runs(arms, runs, today)
    if not stale:
        return []
    return [f"Stale: {', '.join(stale)}, {grid.STALE_WHY}. Their figures here are not today's experiment.", ""]


def plot_results(out: str, arms: Sequence[Arm], source_dir: str, title: str, last_n: int,
                 today: dict[str, str | None]) -> str | None:
    """success.png/.csv in `out` from the arms that have epochs; returns the text of table.md (None if none has),
    naming the stale runs (`stale_note`)."""
    loaded = {arm.name: r for arm in arms if (r := grid.loaded(arm.run_dir))}
    targets = [arm for arm in arms if arm.name != "source"]
    runs = {arm.name: loaded[arm.name] for arm in targets if arm.name in loaded}
    if not runs:
        return None
    curves = report.curves(list(runs.values()), labels={r["dir"]: name for name, r in runs.items()})
    grid.write_figure(curves, os.path.join(out, "success"), title)
    notes = [
        f"# {TARGET_ENV}: {title}",
        "",
        "Success is the seed mean of each epoch's eval success; a threshold is reached at the first epoch whose "
        "mean is at least it. Times are each run's seconds of training (`wall_time`), compilation not counted: the "
        "arms' programs are the same, and the persistent compilation cache spares the second of them most of its "
        "compiling. AUC is the mean success over the epochs run.",
        "",
        results_table(curves, last_n),
        "",
        grid.gaps(targets, runs),
        "",
        *stale_note(arms, loaded, today),
        *grid.fresh_buffer_note({name: run["config"] for name, run in runs.items()}),
    ]
    by_label = {c.label: c for c in curves}
    if {"transfer", "scratch"} <= set(by_label):
        notes += difference_notes(by_label["transfer"], by_label["scratch"], short_note(targets, runs))
    source = loaded.get("source") or grid.loaded(source_dir)  # a --source run is no arm
    if source is not None:
        notes.append(
            f"Source: {source['env']} {source['agent']} in {source_dir}, {len(source['epoch'])} epochs, "
            f"{source['env_steps'][-1]:,.0f} env steps per seed, {source['wall_time'][-1]:,.0f} s (not in the times "
            f"above); final seed-mean success {source['success'][-1].mean():.3f}."
        )
    return "\n".join(notes) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    args, rest = build_parser().parse_known_args(argv)
    try:
        extra = grid.pass_through(rest, PROG)
        out = grid.out_dir(args, "transfer", extra)
        cluster.prepare_driver(args)
        multihost.initialize()
        train_names = parse_arms(args.arms)
        arms = grid.checked_arms(make_arms(args, extra, out), args.last_n)
    except ConfigError as err:
        return cli.exit_code(err)
    envs = grid.make_envs(arms)
    try:
        print(grid.estimated_plan(arms, envs), flush=True)
    except ConfigError as err:  # a damaged run folder (`report.RunError`)
        return cli.exit_code(err)
    if args.dry_run:
        print(grid.DRY_RUN)
        return 0
    # the transfer arm starts from the source's parameters: a stale source is refused too, trained or not
    source = [arm for arm in arms if arm.name == "source" and "transfer" in train_names]
    try:
        grid.refuse_stale(source, envs)
        refuse_unfinished_source(arms, train_names)
        code = grid.train_arms([arm for arm in arms if arm.name in train_names], envs, args, out)
    except ConfigError as err:
        return cli.exit_code(err)
    if code:  # a refusal or a failed run ends the command on its error line (`--arms none` writes the table)
        return code
    variant = ", no held starts" if out.endswith(grid.PLAIN) else ""
    title = f"from scratch vs. from {SOURCE_ENV} ({args.seeds} seeds{variant})"  # the panel names the task
    if multihost.is_main():  # one process writes the results
        try:
            today = {arm.given["env"]: envs[arm.name].physics_id for arm in arms}
            text = plot_results(out, arms, source_dir(args, out), title, args.last_n, today)
            command = regenerate_command(args, out)
            grid.write_table(out, text and f"{text}\nRegenerate from the run folders: `{command}`\n")
        except cli.FAILURES as err:  # a damaged run folder (exit 2), a failed write of the results (exit 4)
            return cli.exit_code(err)
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
