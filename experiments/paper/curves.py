"""The learning curves (paper Fig. 4): every agent on every task, the same budget for
every agent of a task.

    python -m experiments.paper.curves [--tasks a,b] [--agents x,y] [--seeds N] [--seed 0] [--epochs N]
        [--out results/curves] [--dry-run | --report] [--last-n 10]
        [any learner or network option of experiments.run]

The grid is the tasks that declare a learning-curve budget (`protocol.paper_tasks`: planar_reach, ur5_reach,
nicol_slide and nicol_lift) × the agents of `bidal_jax.agents.AGENTS` (the paper's five and multimodal_bidal_no_ri,
multimodal BidAL without its intrinsic reward: whether a gain comes from the representation losses or from the
curiosity reward); `--tasks` and `--agents` (comma lists) take a part of it, and `--tasks` any other registered task
where `--epochs` gives its budget. Each cell is 5 seeds of one task and agent (`--seeds N` sets every cell's) in
OUT/<task>/<agent>, trained in blocks of seeds vmapped as one program that each end within `protocol.BLOCK_SECONDS`
on one GPU by the plan's estimate (`grid.blocks`): a cell that fits is one run in its folder, a longer one is runs
in OUT/<task>/<agent>/seeds-A-B with their own first seed, which the table, the figure and the claims read as one
run of all its seeds (`report.load_run`).

Budget: one epoch count per task for every agent, the task's own (its env's `task.paper_epochs`,
`protocol.paper_epochs`; overridden for all tasks by `--epochs`): planar_reach 100, ur5_reach 150, nicol_slide 30,
nicol_lift 25, where the slowest agent that learns levels off in pilot runs, plus a margin (docs/deviations.md,
"Learning-curve budgets"). The NICOL tasks' are their env presets' (envs_mjx/nicol.py); the reaching tasks' presets
(planar_reach 40, 20 for its image agents; ur5_reach 15) are sized for a run on a CPU, so the grid runs them until
the visual agents' curves level off, the same for every agent so that every curve of a panel covers the same env
steps. The other settings are the env presets' (nicol_slide: 2,560 envs × 1 cycle, nicol_lift: 2,048 × 2, ...);
learner and network options (e.g. `--num-envs 16 --conv-channels 4`) and `--checkpoint-every` pass to every run.

nicol_lift trains under HER's pick-and-place protocol, its preset's: half of its training episodes start with the
cube held, evaluation always from reset (the paper is silent; docs/deviations.md). `--exploration-starts 0` runs
the plain protocol instead, a labelled variant written to results/curves-plain by default.

`--dry-run` prints the plan (one line per run: task, agent, seeds, epochs, env steps per seed,
run dir, new/resume/done/stale) and its estimated time on one GPU running the runs one after another
(`grid.epoch_time`, measured epochs in results/scaling/epochs), and writes nothing. Otherwise the runs
train one after another (`experiments/paper/grid.py`), resumable as experiments.paper.transfer_learning: run
the same command again; a run whose latest checkpoint, or whose metrics.csv (results/ keeps no finished run's
checkpoints), is at its epochs is skipped, an interrupted one resumes from its latest checkpoint (with an empty
replay buffer; a checkpoint without it is refused unless `--fresh-buffer`), one without a checkpoint
starts again. `--ray` trains the runs as cells of Ray tasks, all at once where the GPUs allow
(`experiments/cluster.py`; docs/usage.md "Clusters (Ray)"), into the same run folders. A stale run
(`grid.stale`: its config.json records other physics than its task's today, or none, or a config that differs
from its arm's today in a field that changes results, e.g. num_envs)
is neither skipped nor resumed: while any run is stale, training refuses to start (exit 2, one
`error: ...` line naming it; nothing trained, no run folder changed): move the stale folders away or
pass another `--out`. Every run compiles into the persistent compilation cache (`cli.start_run`), so a run
resumed or repeated where its program is cached compiles in less time; its `wall_time_with_compile`
(metrics.csv; `wall_time` starts after compiling) holds whatever compiling took.

Then, from whatever runs have epochs, it writes into OUT `curves.png` and `curves.csv` (one panel
per task, one line per agent: eval success against env steps per seed, mean ± std over seeds;
`experiments/report.py`) and `table.md` (final success, mean ± std over seeds of each seed's last
`--last-n` epochs, per agent and task, with how many seeds are above the task's floor and the floors below; each
run's wall time with its compilation, the machine time they held and their summed time, and the runs missing
or unfinished; a run whose metrics.csv predates `wall_time_with_compile` shows its
`wall_time`, marked "*": compilation not counted; a stale run's cell is marked "†", and a line below
the table counts them; another names the runs resumed with an empty replay buffer, `grid.fresh_buffer_note`,
and the epochs a run's metrics.csv lacks; last, the command that regenerates them, `regenerate_command`). `--report`
trains nothing and writes only these, e.g. from run folders whose checkpoints were not kept (results/ keeps none but
none: .gitignore).

Exit codes as experiments.run: 0 done; 2 bad option, config or checkpoint (one `error: ...`
line, nothing written), or a stale run (one `error: ...` line, nothing trained), or a run folder with a damaged file
(one line naming it: the experiment stops rather than take the run for one never trained); 3 diverged; 4 the disk (a
run's write, or table.md or the figure); 6 out of device memory; 130 and 143 stopped by SIGINT and SIGTERM (a
checkpoint was saved; Ctrl-C before a run trains: nothing saved). A refusal or a failed run ends the command with its
error as the last line (with `--ray`, the line listing the cells that failed): nothing is plotted or tabled after it;
`--report` writes the table and figure from the runs that have epochs.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from typing import Any, Collection, Sequence

import envs_mjx
from bidal_jax.config import AGENTS, ConfigError, option
from bidal_jax.run import multihost
from experiments import cli, cluster, report
from experiments.paper import grid, protocol
from experiments.paper.grid import Arm
from experiments.paper.protocol import DEFAULT_SEED, DEFAULT_SEEDS

PROG = "python -m experiments.paper.curves"
LIFT = "nicol_lift"


def build_parser() -> argparse.ArgumentParser:
    parser = grid.experiment_parser(PROG, __doc__, "every run")
    budgets = protocol.paper_epochs()
    parser.add_argument("--tasks", default=",".join(budgets), help=f"comma list of tasks (default all that declare a "
                        f"learning-curve budget: {', '.join(budgets)}; another registered task needs --epochs)")
    parser.add_argument("--agents", default=",".join(AGENTS), help=f"comma list of agents (default all: "
                        f"{', '.join(AGENTS)})")
    parser.add_argument("--seeds", type=int, default=DEFAULT_SEEDS, help="seeds of every cell, in blocks of seeds "
                        "vmapped as one program")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="first random seed of every run")
    parser.add_argument(
        "--epochs",
        type=int,
        default=None,
        help="epochs of every run of every task (default per "
        "task: " + ", ".join(f"{t} {e}" for t, e in budgets.items()) + ")",
    )
    parser.add_argument("--out", default=None, help="output folder (default results/curves, or results/curves-plain "
                        "with --exploration-starts 0)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--dry-run", action="store_true", help="print the plan and its estimated time; write nothing")
    mode.add_argument(
        "--report",
        action="store_true",
        help="train nothing: write curves.png/.csv and table.md from the run folders that have epochs",
    )
    parser.add_argument("--last-n", type=int, default=10, help="epochs averaged for the final success in table.md")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def chosen_tasks(text: str, epochs: int | None) -> tuple[str, ...]:
    """The registered tasks of `--tasks`; ConfigError for a name not registered, or for one without a learning-curve
    budget (`protocol.paper_epochs`) unless `epochs` (`--epochs`) gives every task's."""
    tasks = cli.parse_names(text, "--tasks", "task", envs_mjx.names())
    without = [task for task in tasks if task not in protocol.paper_epochs()]
    if without and not epochs:
        raise ConfigError(f"--tasks {text}: {', '.join(without)} declares no learning-curve budget (its env's "
                          "task.paper_epochs); give --epochs N")
    return tasks


def plan_text(blocks: Sequence[Arm], envs: dict[str, Any]) -> str:
    """The plan: one line per block of seeds with its estimated time (`grid.estimated_plan`), then the estimated
    total, and the stale runs' count."""
    return grid.estimated_plan(blocks, envs, f"plan: {len(blocks)} runs", named=False)


def seconds(run: dict) -> str:
    """The run's last time with its compilation (`report.last_time`), or its `wall_time` marked "*"."""
    time, with_compile = report.last_time(run)
    return f"{time:,.0f} s" + ("" if with_compile else "*")


def cell(run: dict, curve: report.Curve, epochs: int, last_n: int, floors: report.Floors) -> str:
    """Final success (mean ± std over seeds of each seed's last `last_n` epochs), how many seeds are clearly above
    the task's floor (`protocol.above_floor`), the run's wall time (`seconds`), and how far it got when it is
    unfinished."""
    done = int(run["epoch"][-1])
    progress = "" if done >= epochs else f", epoch {done} of {epochs}"
    above = protocol.above_floor(run, floors, last_n)
    return f"{report.final_cell(curve, last_n)}{f' ({above})' if above else ''}, {seconds(run)}{progress}"


def results_table(arms: Sequence[Arm], runs: dict[str, dict], last_n: int, stale: Collection[str] = (),
                  floors: report.Floors | None = None) -> str:
    """Markdown: one row per agent, one column per task, then the tasks' floors (`report.load_floors`, over all
    goals); a run without epochs is "—", one of `stale` (arm names) is marked `grid.STALE`."""
    floors = report.load_floors() if floors is None else floors
    tasks = {arm.given["env"]: arm.epochs for arm in arms}
    agents = list(dict.fromkeys(arm.given["agent"] for arm in arms))
    by_dir = {c.run_dir: c for c in report.curves(list(runs.values()))}
    head = ["agent", *(f"{task} ({epochs} epochs)" for task, epochs in tasks.items())]
    rows = []
    for agent in agents:
        cells = [agent]
        for arm in (a for a in arms if a.given["agent"] == agent):
            run = runs.get(arm.name)
            mark = grid.STALE if arm.name in stale else ""
            cells.append("—" if run is None else cell(run, by_dir[run["dir"]], arm.epochs, last_n, floors) + mark)
        rows.append(cells)
    rows.append(["floor: a policy that does nothing", *(report.floor_value(floors, task) for task in tasks)])
    return report.markdown_table(head, rows)


def stale_note(stale: Collection[str], cells: int) -> list[str]:
    """The line below the table that says what `grid.STALE` marks and how many of its `cells` it marks; none
    when no run is stale."""
    if not stale:
        return []
    return [
        f"{grid.STALE} stale: {len(stale)} of {cells} cells, {grid.STALE_WHY}.",
        "",
    ]


def regenerate_command(args: argparse.Namespace, rest: Sequence[str], out: str) -> str:
    """The command that rewrites curves.png/.csv and table.md from the run folders alone: `--report` with the
    options that choose the runs, their budget and the window of the final success, and the learner and network
    options passed through `rest` (they set the configs the stale check compares)."""
    parser = build_parser()
    chosen = [f"{option(name)} {getattr(args, name)}" for name in ("tasks", "agents", "seeds", "seed", "epochs",
                                                                          "last_n")
              if getattr(args, name) != parser.get_default(name)]
    return " ".join([PROG, "--report", *chosen, *map(shlex.quote, rest), f"--out {out}"])


def lift_note(arms: Sequence[Arm], runs: dict[str, dict], last_n: int) -> list[str]:
    """The lines below the table on lifting: per agent on nicol_lift, its final success over air goals beside what
    a policy that never lifts scores there, and how many of its seeds lift (`protocol.seeds_that_lift`); none
    without a nicol_lift run that reports air goals."""
    cells = [(arm.given["agent"], run) for arm in arms if arm.given["env"] == LIFT
             and (run := runs.get(arm.name)) is not None and run["success_air"] is not None]
    if not cells:
        return []
    floor = envs_mjx.make(LIFT, render=False).never_lift_success()["air"]
    finals = [(agent, run["success_air"][-last_n:].mean(axis=0)) for agent, run in cells]
    parts = [f"{agent} {final.mean():.3f}, {protocol.seeds_that_lift(final)} of {final.size} seeds lift"
             for agent, final in finals]
    idle = report.floor_value(report.load_floors(), LIFT, "air")
    return [f"{LIFT}, air goals alone (evaluation from reset; a policy that never lifts scores {floor:.3f}, one that "
            f"does nothing {idle}): final "
            f"success over the last {last_n} epochs and the seeds that lift (their air-goal success ≥ "
            f"{protocol.LIFTS} there): " + "; ".join(parts) + ".", ""]


def plot_results(out: str, arms: Sequence[Arm], title: str, last_n: int, today: dict[str, str | None],
                 command: str) -> str | None:
    """curves.png/.csv in `out` from the runs that have epochs; returns the text of table.md (None
    if none has), its stale runs marked (`today`: env name -> its physics fingerprint today), ending with
    `command`, which regenerates them."""
    runs = {arm.name: r for arm in arms if (r := grid.loaded(arm.run_dir))}
    if not runs:
        return None
    stale = grid.stale_runs(arms, runs, today)
    grid.write_figure(report.curves(list(runs.values())), os.path.join(out, "curves"), title)
    held, total = report.machine_time(list(runs.values()))
    return "\n".join([
        f"# {title}",
        "",
        f"Final success: the mean ± std over seeds of each seed's mean eval success over its last {last_n} epochs, "
        "with how many seeds are clearly above the task's floor (the last row: what a policy that does nothing "
        "scores, results/floors; a one-sided binomial test of each seed's successes in those epochs' eval episodes "
        "against the floor estimate's upper 95 % bound, "
        "Holm over the run's seeds, α = 0.05); then the run's wall time (its last `wall_time_with_compile`, "
        "compilation included; * its last "
        "`wall_time`, compilation not counted, where metrics.csv predates that column).",
        "",
        results_table(arms, runs, last_n, stale),
        "",
        *lift_note(arms, runs, last_n),
        *stale_note(stale, len(runs)),
        *grid.fresh_buffer_note({name: run["config"] for name, run in runs.items()}),
        f"Machine time the runs held: {grid.duration(held)} of GPU time (wall time × the GPUs of their machine, runs "
        "that shared a GPU counted once as results/*/figures.json records them, `report.machine_time`); their summed "
        f"process time: {grid.duration(total)}.",
        "",
        grid.gaps(arms, runs),
        "",
        f"Regenerate from the run folders: `{command}`",
        "",
    ])


def main(argv: Sequence[str] | None = None) -> int:
    args, rest = build_parser().parse_known_args(argv)
    try:
        extra = grid.pass_through(rest, PROG)
        out = grid.out_dir(args, "curves", extra)
        cluster.prepare_driver(args)
        multihost.initialize()
        tasks = chosen_tasks(args.tasks, args.epochs)
        agents = cli.parse_names(args.agents, "--agents", "agent", tuple(AGENTS))
        arms = grid.curve_arms(tasks, agents, args.seeds, args.seed, args.epochs, extra, out)
        cells = grid.checked_arms(arms, args.last_n)
        blocks = [block for cell in cells for block in grid.blocks(cell)]
    except ConfigError as err:
        return cli.exit_code(err)
    envs = None
    try:
        if not args.report:
            envs = grid.make_envs(blocks)
            print(plan_text(blocks, envs), flush=True)
            if args.dry_run:
                print(grid.DRY_RUN)
                return 0
            code = grid.train_arms(blocks, envs, args, out)
            if code:  # a refusal or a failed run ends the command on its error line (`--report` writes the table)
                return code
        variant = f", {LIFT} without held starts" if out.endswith(grid.PLAIN) else ""
        title = f"Eval success against env steps per seed, mean ± std over seeds{variant}"
        if multihost.is_main():  # one process writes the results
            # each task's physics today: of the envs built to train, else (--report) built for it
            today = ({block.given["env"]: envs[block.name].physics_id for block in blocks} if envs
                     else grid.physics_today(cell.given["env"] for cell in cells))
            grid.write_table(out, plot_results(out, cells, title, args.last_n, today,
                                               regenerate_command(args, rest, out)))
    except cli.FAILURES as err:  # a damaged run folder (exit 2), a failed write of the results (exit 4)
        return cli.exit_code(err)
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
