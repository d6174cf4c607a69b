"""Noise robustness (paper Sec. IV-B, Table II): `python -m experiments.paper.noise_robustness`.

Trains multimodal_bidal, multimodal_baseline and proprio_baseline on nicol_slide with
observation noise s + κ·N(0, σ) on `ee_pos`, `ee_rot` and `obj_pos` (σ: each feature's
interquartile range over the clean history; `bidal_jax/noise.py`) at κ = 5, 10 and 15 %,
5 runs each. Per agent, the 3 κ × 5 runs are ONE compiled program: 15 vmapped runs whose κ
is data in the training state (run i has κ_{i // 5} and its own seed key). `--kappas 0.10,0.15`
instead trains each named κ as its own program of 5 runs into `<agent>-kappa10/` ... (about a
third of the time each, so that one fits a half-hour job); the table reads both
layouts, and the same κ in both is refused.

Writes into `--out` (default results/noise): one run directory per agent (`<agent>/`,
metrics.csv with `eval_success_seed0..14`), `table.md` (the paper's Table II: per κ and
agent, the mean over the 5 runs of each run's mean success over its last N epochs, N = 5 at
5 % and 30 at 10 and 15 %, ± the std over the runs, beside the paper's figures; a run with fewer
epochs than its budget (`protocol.budget`: the env and agent preset's, or its config's if more) is marked
"short run", and the task's floor, what a policy that does nothing scores (results/floors); then the steadiness
of claim (b): each run's residual std around its own fitted linear trend over those N epochs, the mean over runs,
beside the runs' mean slope per epoch with its 95 % interval, "still climbing" where that interval excludes 0 (the
spread then is not the steadiness the paper compares; `protocol.residual_spread`, `protocol.trending`); and the
command that regenerates it),
`curves.png` and `curves.csv` (one panel per κ, one line per agent, mean ± std over the 5 runs).
`--report` trains nothing and writes only these, from the run folders (results/ keeps no
checkpoints: training again there would start the runs afresh). `--dry-run` prints the plan, each
program with its state (new, resume, done or stale) and its estimated time (`grid.estimated_plan`), and trains
and writes nothing.

Resumable: a finished agent is skipped, an interrupted one resumed from its latest
checkpoint, and a stale one (`grid.stale`: made on other physics or with another config) refused
before any agent trains; the table and plot are made from whatever metrics exist. `--epochs`, `--agents`
and the size options (`--num-envs` ...) allow a shorter or smaller run; the defaults are
the nicol_slide preset's; `--ray` trains the programs as cells of Ray tasks, all at once where the
GPUs allow (`experiments/cluster.py`). The agents' runs are trained by `experiments/paper/grid.py` (as the
transfer and curves experiments), so the exit codes are experiments.run's: 0 done; 2 bad
option, config or checkpoint, or a run folder with a damaged file (one line naming it; the experiment stops on
it); 3 diverged; 4 the disk (a run's write, or table.md or the figure); 130 and 143 stopped by SIGINT and SIGTERM.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

import envs_mjx
from bidal_jax.config import ConfigError
from bidal_jax.run import multihost, rundir, runfiles
from experiments import cli, cluster, report
from experiments.paper import grid
from experiments.paper.grid import Arm
from experiments.paper.protocol import (
    DEFAULT_SEED,
    KAPPAS,
    LAST_N,
    NOISE_ENV,
    NOISE_EPOCHS,
    PAPER,
    SEGMENTS,
    kappa_dir,
    load_noise_curves,
    residual_spread,
    trend_text,
    trending,
)
from experiments.paper.protocol import (
    NOISE_AGENTS as AGENTS,
)

PROG = "python -m experiments.paper.noise_robustness"
SIZE_OPTIONS = ("num_envs", "cycles_per_epoch", "updates_per_cycle", "batch_size", "buffer_episodes", "eval_envs")


def run_kappas(runs: int, kappas: Sequence[float] = KAPPAS) -> np.ndarray:
    """κ of each vmapped run: kappas[i // runs]."""
    return np.repeat(np.asarray(kappas, np.float32), runs)


def noise_arm(agent: str, run_dir: str, given: dict, kappas: np.ndarray) -> Arm:
    """One program of len(kappas) vmapped runs of `agent` in `run_dir`: a run whose fresh state gets run i's κ
    from `kappas`; named after its folder."""
    kappa = jnp.asarray(kappas)

    def with_kappas(state):
        return state.replace(noise=state.noise.replace(kappa=kappa))

    given = {**given, "agent": agent, "run_dir": run_dir, "seeds": len(kappas)}
    return Arm(os.path.basename(run_dir), given, initialize=with_kappas)


def make_arms(agents: Sequence[str], kappas: Sequence[float] | None, out: str, given: dict, runs: int) -> list[Arm]:
    """Per agent one program of 3 κ × `runs` in OUT/<agent> (`kappas` None), or one of `runs` per κ in `kappas`
    in OUT/<agent>-kappaNN (`protocol.kappa_dir`)."""
    if kappas is None:
        return [noise_arm(agent, os.path.join(out, agent), given, run_kappas(runs)) for agent in agents]
    return [noise_arm(agent, os.path.join(out, kappa_dir(agent, k)), given, run_kappas(runs, (k,)))
            for agent in agents for k in kappas]


def parse_kappas(text: str) -> tuple[float, ...]:
    """`--kappas 0.10,0.15` -> the paper's κ it names, in its order; raises ConfigError for another value."""
    named = {f"{k:.2f}": k for k in KAPPAS}
    try:
        return tuple(named[f"{float(item):.2f}"] for item in text.split(","))
    except (KeyError, ValueError):
        raise ConfigError(f"--kappas {text}: must be a comma list of {', '.join(named)}") from None


def window_note(rows: int, reached: int, budget: int, last_n: int) -> str:
    """" (19 epochs)" for a run whose metrics.csv has 19 rows; " (last 19 of 19 epochs)" when those are fewer
    than the window; "; 5 epochs without a row" when it `reached` more epochs than it has rows (rows lost outside
    the run: `report.absent_epochs`); "; short run: 19 of 100 epochs" when `reached` is below its `budget` (its
    config's epochs)."""
    window = f"last {rows} of {rows} epochs" if rows < last_n else f"{rows} epochs"
    lost = f"; {reached - rows} epochs without a row" if rows < reached else ""
    return f" ({window}{lost}" + (f"; short run: {reached} of {budget} epochs" if reached < budget else "") + ")"


def table(curves: dict[tuple[float, str], report.Curve], budgets: dict[str, int], floors: report.Floors) -> str:
    """Table II beside the paper's: ours (mean ± std over runs of each run's last-N mean) | paper, the task's floor
    below; then the steadiness (`residual_spread`, mean over runs, with the runs' slope: `trend_text`, marked where
    `trending`) beside the paper's ±. `budgets`: each agent's epochs."""
    agents = [a for a in AGENTS if any(agent == a for _, agent in curves)]
    head = ["κ", "N", *(f"{a} ({whose})" for a in agents for whose in ("ours", "paper"))]
    steady_head = ["κ", "N", *(f"{a} ({whose})" for a in agents for whose in ("ours", "paper's ±"))]
    rows, steady_rows = [], []
    for k in KAPPAS:
        cells, steady = [f"{k:.0%}", str(LAST_N[k])], [f"{k:.0%}", str(LAST_N[k])]
        for a in agents:
            curve = curves.get((k, a))
            if curve is None:
                cells.append("— ")
                steady.append("— ")
            else:
                mean, std, _ = report.final_success(curve, LAST_N[k])
                note = window_note(len(curve.epoch), int(curve.epoch[-1]), budgets[a], LAST_N[k])
                cells.append(f"{mean:.3f} ± {std:.4f}{note}")
                climbing = "; still climbing" if trending(curve, LAST_N[k]) else ""
                steady.append(f"{residual_spread(curve, LAST_N[k]).mean():.4f} (slope "
                              f"{trend_text(curve, LAST_N[k])}{climbing})")
            cells.append("{:.3f} ± {:.4f}".format(*PAPER[k][a]))
            steady.append(f"{PAPER[k][a][1]:.4f}")
        rows.append(cells)
        steady_rows.append(steady)
    return "\n".join([
        report.markdown_table(head, rows),
        "",
        f"{NOISE_ENV}'s {report.floor_text(floors, NOISE_ENV)}: what a policy that does nothing scores "
        "(results/floors).",
        "",
        "Steadiness: each run's residual std of its success around its own fitted linear trend over the same last N "
        "epochs, the mean over runs (paper Sec. IV-B compares its ± as \"the mean standard deviation\" of the "
        "success rate; it does not say over what); beside it the runs' fitted slope, their mean with its Student-t "
        "95 % interval over runs. \"Still climbing\": that interval excludes 0, so the curves have not levelled off "
        "in the window and the steadiness is not measured there (claim (b) says so).",
        "",
        report.markdown_table(steady_head, steady_rows),
        "",
    ])


def write_report(out: str) -> str:
    """Write table.md, curves.png and curves.csv from the agents' run directories; return the table."""
    found, budgets = load_noise_curves(out)
    if not found:
        return ""
    grid.write_figure(list(found.values()), os.path.join(out, "curves"), "nicol_slide under observation noise")
    run_dirs = dict.fromkeys(curve.run_dir for curve in found.values())  # the folders read, in the table's order
    configs = {os.path.basename(d): grid.loaded(d)["config"] for d in run_dirs}
    resumed = "\n".join(grid.fresh_buffer_note(configs))
    absent = report.absent_note({os.path.basename(curve.run_dir): curve.epoch for curve in found.values()})
    lost = f"{absent}\n" if absent else ""
    text = (f"{table(found, budgets, report.load_floors())}\n{lost}{resumed}Regenerate from the run folders: "
            f"`{PROG} --report --out {out}`\n")
    path = os.path.join(out, "table.md")
    with rundir.writing(path):
        runfiles.write_atomic(path, text)
    return text


def report_or_error(write: Callable[[], None]) -> int:
    """Run `write` (the plan, or the table from the run folders); a folder it cannot read (a κ in both layouts, a
    run folder damaged outside its run: `report.RunError`) is one `error: ...` line and exit code 2, a failed write
    of the table or figure (`rundir.writing`) one line and 2 or 4, also after training (whose runs are kept)."""
    try:
        write()
    except (ConfigError, rundir.DiskError) as err:  # report.RunError is a ConfigError
        return cli.exit_code(err)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=os.path.join("results", "noise"), help="results folder")
    parser.add_argument("--env", default="nicol_slide", choices=envs_mjx.names())
    parser.add_argument("--agents", nargs="+", default=list(AGENTS), choices=AGENTS)
    parser.add_argument("--runs", type=int, default=5, help="runs (seeds) per κ")
    parser.add_argument("--kappas", default=None,
                        help="comma list of κ, each trained as its own program of --runs runs into "
                        "OUT/<agent>-kappaNN (about a grid cell's time, where all three κ in one program take "
                        "three); default: all three κ in one program per agent, in OUT/<agent>")
    parser.add_argument("--epochs", type=int, default=None, help=f"epochs per run (default {NOISE_EPOCHS}: "
                        "the widest window of the final success after the curves level off)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--noise-segments", default=SEGMENTS, help="proprio segments that get noise")
    for name in SIZE_OPTIONS:
        parser.add_argument("--" + name.replace("_", "-"), type=int, default=None, help="(default: the env preset's)")
    parser.add_argument("--checkpoint-every", type=int, default=None,
                        help="save a checkpoint every K epochs (default: the run's; a run's checkpoints on the "
                        "nicol_slide preset are GBs, and their cadence does not make a run stale)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--report", action="store_true", help="train nothing: write table.md, curves.png and "
                      "curves.csv from the run folders in --out")
    mode.add_argument("--dry-run", action="store_true", help="print the plan (each program's state: new, resume, "
                      "done or stale); train and write nothing")
    parser.add_argument("--quiet", action="store_true")
    grid.add_training_options(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    given = {"env": args.env, "seed": args.seed, "noise_segments": args.noise_segments,
             **{k: getattr(args, k) for k in (*SIZE_OPTIONS, "checkpoint_every") if getattr(args, k) is not None}}
    given["epochs"] = args.epochs or NOISE_EPOCHS
    if args.report:
        return report_or_error(lambda: print(write_report(args.out) or f"no noise runs in {args.out}: nothing written"))
    try:
        if args.runs < 1:
            raise ConfigError(f"--runs {args.runs}: must be a positive integer")
        kappas = None if args.kappas is None else parse_kappas(args.kappas)
        for agent in args.agents if kappas else ():
            if os.path.isfile(os.path.join(args.out, agent, "metrics.csv")):
                raise ConfigError(f"--kappas {args.kappas}: {os.path.join(args.out, agent)} already holds every κ "
                                  f"of {agent}; train them in another --out")
        cluster.prepare_driver(args)
        multihost.initialize()
    except ConfigError as err:
        return cli.exit_code(err)
    programs = (f"one program of {len(KAPPAS) * args.runs} runs per agent" if kappas is None
                else f"one program of {args.runs} runs per agent and κ")
    print(f"noise experiment: {args.env}, agents {', '.join(args.agents)}, κ {kappas or KAPPAS} × {args.runs} runs "
          f"each ({programs}), {given['epochs']} epochs, into {args.out}")
    arms = make_arms(args.agents, kappas, args.out, given, args.runs)
    envs = grid.make_envs(arms)
    code = report_or_error(lambda: print(grid.estimated_plan(arms, envs), flush=True))  # a damaged run folder: exit 2
    if code:
        return code
    if args.dry_run:
        print(grid.DRY_RUN)
        return 0
    os.makedirs(args.out, exist_ok=True)
    code = grid.train_arms(arms, envs, args, args.out)
    if code:
        return code
    if multihost.is_main():  # one process writes the results, from every run folder in --out (other programs' too)
        return report_or_error(lambda: print(write_report(args.out)))
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
