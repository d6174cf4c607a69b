"""Runs of a paper experiment, trained one after another and resumable (`curves`,
`noise_robustness`, `transfer_learning`).

An experiment is a list of `Arm`s: a name and the config fields of one run (`run_dir` and
`epochs` resolved). `status` says what running it again does: "done" (its latest checkpoint is
at its epochs: skipped), "resume" (an earlier checkpoint: continued from it with its replay buffer; a checkpoint
without its buffer is refused unless `--fresh-buffer`, a labelled deviation, resumes it with an empty one), "new" (no
checkpoint: its directory is deleted and it starts again) or "stale" (its folder holds epochs of
a run on other physics or with another config than the arm's today, `stale`: refused). `train_arms`
trains them in-process one after another (`cli.start_run`), or with `--ray` as cells of Ray tasks
(`experiments.cluster`), and returns the exit code of experiments.run (`cli.exit_code`):
0 done; 2 bad config or checkpoint, a stale run (refused before any run trains; no folder is deleted
or written), or a run directory in use (one `error: ...` line); 3 diverged; 4 the disk
(no room for a checkpoint, or a write failed); 130 and 143 stopped by SIGINT and SIGTERM (a
checkpoint was saved). Each run locks its own directory while it trains (`bidal_jax.run.rundir`),
not the experiment's folder: two commands may share the folder (e.g. `experiments.paper.transfer_learning
--arms source` and `--arms scratch`), but a run that another process trains is refused (exit 2). Every
experiment's plan (`estimated_plan`) gives each run's estimated time on one GPU from the epochs measured in
results/scaling/epochs (`epoch_time`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import os
from typing import Any, Callable, Iterable, NamedTuple, Sequence

import envs_mjx
from bidal_jax.config import AGENTS, CONFIG_CLASSES, Config, ConfigError, NetworkConfig, TrainConfig, option, recorded
from bidal_jax.run import checkpoint, memory, rundir, runfiles, validate
from bidal_jax.run.checkpoint import CheckpointError
from experiments import cli, cluster, report
from experiments.paper.protocol import BLOCK_SECONDS, DEFAULT_SEEDS, paper_epochs
from experiments.report import loaded  # the experiments read their runs through it, as `grid.loaded`

# what passes through to every run: the learner and network options and the checkpoint interval
PASS_THROUGH = frozenset({f.name for cls in (TrainConfig, NetworkConfig) for f in dataclasses.fields(cls)}) \
    | {"checkpoint_every"}
PLAIN = "plain"  # the suffix of an experiment's folder when its lifting runs start no episode held
# config fields that cannot change what a run learns or reports, so `stale` does not compare them: where it is
# written (run_dir) and where its transfer source lies (init_from: a path; the source's own config is its
# folder's), how often it saves a checkpoint, how its envs are laid out across devices (env_shards: its
# random draws differ, not its budget, data or learner), how its convs are computed (conv_impl: the same
# function and parameters, float rounding apart) and its physics engine (physics: the same model and fingerprint)
NOT_COMPARED = frozenset({"run_dir", "init_from", "checkpoint_every", "env_shards", "conv_impl", "physics"})
DRY_RUN = "dry run: nothing trained or written"  # the last line of every experiment's --dry-run


@dataclasses.dataclass(frozen=True)
class Arm:
    """One run of an experiment: its name, its config fields, what a fresh start does to the
    initial state (`initialize`, e.g. the noise experiment's κ per seed; by default the transfer's
    restore when the run has `init_from`, else nothing), and the arms it starts after when Ray
    schedules them (`after`, by name: the transfer arm starts from its source's parameters)."""

    name: str
    given: dict[str, Any]
    initialize: Callable[[Any], Any] | None = None
    after: tuple[str, ...] = ()

    @property
    def run_dir(self) -> str:
        return self.given["run_dir"]

    @property
    def epochs(self) -> int:
        return self.given["epochs"]

    @property
    def config(self) -> Config:
        """The run's config: defaults, presets, then its fields."""
        return cli.resolve(self.given)


STALE = "†"  # marks a stale run's cell (`stale`) in the learning curves' tables
STALE_WHY = ("runs not recorded on today's physics of their task or made with another config than their arm's today "
             "(`grid.stale` in experiments/paper/grid.py; `--dry-run` says why); training refuses them until their "
             "folders are moved away")


def curve_arms(tasks: Sequence[str], agents: Sequence[str], seeds: int, seed: int, epochs: int | None,
               extra: dict[str, Any], out: str) -> list[Arm]:
    """The learning-curve grid's cells (`experiments.paper.curves`) in OUT/<task>/<agent>, task by task in the
    registry's order, each with `epochs` or else its task's budget (`protocol.paper_epochs`) for every agent (training
    splits them into blocks of seeds, `blocks`)."""
    budgets = {} if epochs else paper_epochs()
    return [Arm(f"{task}/{agent}", {"env": task, "agent": agent, "seeds": seeds, "seed": seed, **extra,
                                    "epochs": epochs or budgets[task], "run_dir": os.path.join(out, task, agent)})
            for task in envs_mjx.names() if task in tasks for agent in AGENTS if agent in agents]


def experiment_parser(prog: str, doc: str, runs: str) -> argparse.ArgumentParser:
    """The parser of an experiment `prog` (described by its module docstring `doc`) whose learner and
    network options pass through to `runs` (`pass_through`), with the options of how its runs train
    (`add_training_options`)."""
    parser = argparse.ArgumentParser(
        prog=prog, description=doc.split("\n\n")[0], allow_abbrev=False,
        epilog="Learner and network options of python -m experiments.run (e.g. --num-envs 16 --conv-channels 4) "
        f"and --checkpoint-every are passed to {runs}.",
    )
    add_training_options(parser)
    return parser


def add_training_options(parser: argparse.ArgumentParser) -> None:
    """How an experiment's runs train: `--fresh-buffer` and the Ray options (`cluster.add_options`)."""
    parser.add_argument("--fresh-buffer", action="store_true",
                        help="resume a run whose latest checkpoint lacks its replay buffer with an empty one (a "
                        "deviation from the uninterrupted run, named below the table); without it such a run is "
                        "refused")
    cluster.add_options(parser)


def pass_through(argv: Sequence[str], prog: str) -> dict[str, Any]:
    """The config fields of the options an experiment `prog` does not know itself, parsed as
    experiments.run parses them; ConfigError for one that is not passed through."""
    parser = cli.run_parser()
    parser.prog = prog
    # unset options are None; flags (--quiet, --resume, ...) are False unless given
    given = {k: v for k, v in vars(parser.parse_args(list(argv))).items() if v is not None and v is not False}
    for name in sorted(set(given) - PASS_THROUGH):
        raise ConfigError(f"{option(name)}: not passed through to the runs (the experiment sets it)")
    return given


def out_dir(args: argparse.Namespace, name: str, given: dict[str, Any]) -> str:
    """--out, or results/NAME (results/NAME-plain for the plain lifting protocol, `--exploration-starts 0`)."""
    plain = given.get("exploration_starts") == 0
    return args.out or os.path.join("results", f"{name}-{PLAIN}" if plain else name)


def checked_arms(arms: list[Arm], last_n: int | None = None) -> list[Arm]:
    """An experiment's runs (made from the options passed through, `pass_through`), with every run's values and
    --last-n, where the experiment has it, checked before the first one trains; ConfigError for a bad one."""
    if last_n is not None and last_n < 1:
        raise ConfigError(f"--last-n {last_n}: must be a positive integer")
    for arm in arms:
        validate.check(arm.config, env_names=envs_mjx.names())
    return arms


def latest(arm: Arm) -> int | None:
    """The epoch the run has reached: its last recorded epoch when its metrics hold all its epochs
    (a finished run whose checkpoints were not kept, as in results/, is done), else the epoch of
    its latest checkpoint (None: it has none)."""
    run = loaded(arm.run_dir)
    if run is not None and run["epoch"][-1] >= arm.epochs:
        return int(run["epoch"][-1])
    return checkpoint.latest_step(os.path.join(arm.run_dir, "checkpoints"))


def status_at(step: int | None, epochs: int) -> str:
    """"done" (`latest` at `epochs`), "resume" (an earlier checkpoint) or "new" (none)."""
    return "new" if step is None else "done" if step >= epochs else "resume"


class Status(NamedTuple):
    """What training does with a run (`state`: "stale", else `status_at`), the epoch it has reached (`latest`)
    and why it is stale (`stale`; None when it is not)."""

    state: str
    step: int | None
    why: str | None


def status(arm: Arm, physics: str | None) -> Status:
    """The run's `Status`: "stale" (`stale`, `physics` today's fingerprint of the arm's env), else its `status_at`
    its latest checkpoint."""
    step, why = latest(arm), stale(arm, physics)
    return Status("stale" if why else status_at(step, arm.epochs), step, why)


def physics_today(envs: Iterable[str]) -> dict[str, str | None]:
    """Env name -> the fingerprint of the physics it steps today (`Env.physics_id`, of an env built without
    rendering: the same model); None for an env no longer registered."""
    return {env: envs_mjx.make(env, render=False).physics_id if env in envs_mjx.names() else None for env in set(envs)}


def other_physics(config: dict, today: str | None) -> str | None:
    """Why a run (its config.json) is not on the physics `today`: "trained on other physics" when it records
    fingerprints (`Env.physics_id`, of the whole model: its camera's pose, field of view and drawn geoms too, so a
    run made with another camera counts; `report.physics_of`) other than `today` alone (a run resumed after a model
    change records both), "physics not recorded" when it records none (runs older than that record); None
    when it is on today's, or `today` is None (an env no longer registered: nothing to compare)."""
    recorded = report.physics_of(config)
    if today is None or recorded == [today]:
        return None
    return "trained on other physics" if recorded else "physics not recorded"


def config_changes(config: dict, today: Config) -> str | None:
    """"config differs: num_envs 512 → 2560, ..." for the fields of a run's config.json whose values differ
    from `today`'s (the arm's resolved config), None when none does. Every field that sets what the run
    learns or reports counts: all of train (the budget and the data: num_envs, cycles_per_epoch,
    updates_per_cycle, batch_size, buffer_episodes, eval_envs; and the learner: learning rates, noise, HER,
    exploration starts, ...), all of network, and of run env, agent, seeds, seed, epochs (the budget the run
    was made for: a run of another one reports other epochs; raising a grid's epochs makes its finished runs
    stale), target_success, init_parts and init_normaliser; not `NOT_COMPARED`. A field the config.json lacks (a
    run older than it) takes what such a run did (`bidal_jax.config.recorded`), as `Config.from_dict` and resuming
    do."""
    changed = []
    for name, group in CONFIG_CLASSES.items():
        fields, ours = recorded(name, config.get(name) or {}), getattr(today, name)
        for field in (f for f in dataclasses.fields(group) if f.name not in NOT_COMPARED):
            was, now = fields.get(field.name, field.default), getattr(ours, field.name)
            if was != now:
                changed.append(f"{field.name} {was} → {now}")
    return f"config differs: {', '.join(changed)}" if changed else None


def stale(arm: Arm, physics: str | None) -> str | None:
    """Why the epochs in the arm's folder do not stand for the arm today (`stale_config` of its config.json,
    `physics` today's fingerprint of its env), or None. A folder without epochs is never stale: it starts again."""
    run = loaded(arm.run_dir)
    return None if run is None else stale_config(run["config"], arm, physics)


def stale_runs(arms: Sequence[Arm], runs: dict[str, dict], today: dict[str, str | None]) -> list[str]:
    """The names of `arms` whose run in `runs` (arm name -> `loaded` run) is stale (`stale_config`), `today`: env
    name -> its physics fingerprint today (`physics_today`)."""
    return [arm.name for arm in arms
            if arm.name in runs and stale_config(runs[arm.name]["config"], arm, today[arm.given["env"]])]


def stale_config(config: dict, arm: Arm, physics: str | None) -> str | None:
    """Why a run of `arm` with this config.json does not stand for the arm today, or None: `other_physics` (not on
    `physics`) and `config_changes` (a field differs from the arm's resolved config), joined by "; "."""
    reasons = [other_physics(config, physics), config_changes(config, arm.config)]
    return "; ".join(r for r in reasons if r) or None


def refuse_stale(arms: Sequence[Arm], envs: dict[str, Any]) -> None:
    """ConfigError, one line, when a run among `arms` is stale (`stale`, against its env's `physics_id` in
    `envs`): the first one's folder and why, the other stale folders, and what to do."""
    found = [(arm, why) for arm in arms if (why := stale(arm, envs[arm.name].physics_id))]
    if found:
        (arm, why), others = found[0], [a.run_dir for a, _ in found[1:]]
        also = f"; also stale: {', '.join(others)}" if others else ""
        raise ConfigError(
            f"{arm.run_dir} is stale ({why}){also}. Nothing was trained and no run folder changed: move the "
            "stale folders away or pass another --out"
        )


def make_envs(arms: Sequence[Arm]) -> dict[str, Any]:
    """Arm name -> its env, rendering only for agents that see images; one env per kind is shared."""
    made: dict[tuple[str, bool], Any] = {}
    envs = {}
    for arm in arms:
        key = (arm.given["env"], arm.config.agent.uses_image)
        if key not in made:
            made[key] = envs_mjx.make(key[0], render=key[1])
        envs[arm.name] = made[key]
    return envs


def plan_line(arm: Arm, env, progress: Status) -> str:
    """What the run is, its epochs and env steps per seed, and what training does with it at its `progress`
    (`status`)."""
    run, train = arm.config.run, arm.config.train
    per_epoch = train.cycles_per_epoch * train.num_envs * env.episode_length
    source = f", parameters from {run.init_from}" if run.init_from else ""
    state, step, why = progress
    carried = " without its replay buffer" if state == "resume" and without_buffer(arm) else ""
    return (
        f"{run.env} {run.agent}, {run.seeds} seed(s), exploration starts {train.exploration_starts:g}{source}; "
        f"{run.epochs} epochs × {per_epoch:,} = {run.epochs * per_epoch:,} env steps per seed in {run.run_dir} "
        f"[{state}" + (f", checkpoint at epoch {step}{carried}]" if state == "resume" else f": {why}]" if why else "]")
    )


# the measured epochs that the estimates read: `python -m experiments.bench.sweep --env TASK --agent AGENT --seeds 5
# --epochs 3 --out results/scaling/epochs/TASK-AGENT.jsonl`, a 5-seed program of the task's preset alone on one GPU,
# one process each from an empty compilation cache (results/scaling/figures.json, "An epoch of each task")
EPOCH_SWEEPS = os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
                            "results", "scaling", "epochs")


class EpochTime(NamedTuple):
    """A 5-seed program's measured seconds per epoch and compile seconds, and the task whose sweep they are."""

    per_epoch: float
    compile: float
    task: str


def read_lines(path: str) -> list[dict]:
    """The JSON objects of a JSON-lines file (`experiments.bench.sweep --out`)."""
    with open(path, encoding="utf-8") as f:
        return [json.loads(line) for line in f if line.strip()]


def sweep_seconds(lines: Sequence[dict]) -> tuple[float, float]:
    """(seconds per epoch: the mean step of `process_seconds`; compile seconds: the first epoch's `variant_seconds`
    less one epoch) of a sweep's JSON lines, one per epoch (`experiments.bench.sweep --out`)."""
    per_epoch = (lines[-1]["process_seconds"] - lines[0]["process_seconds"]) / (len(lines) - 1)
    return per_epoch, lines[0]["variant_seconds"] - per_epoch


@functools.cache
def measured_epochs(folder: str = EPOCH_SWEEPS) -> dict[tuple[str, str], tuple[float, float]]:
    """(task, agent) -> `sweep_seconds` of each sweep TASK-AGENT.jsonl in `folder` of `DEFAULT_SEEDS` seeds and
    several epochs; none where the folder is missing (an installed package without results/)."""
    found = {}
    for name in sorted(os.listdir(folder)) if os.path.isdir(folder) else ():
        lines = read_lines(os.path.join(folder, name)) if name.endswith(".jsonl") else []
        task, _, agent = name.removesuffix(".jsonl").partition("-")
        if len(lines) > 1 and len(lines[0]["eval_success_seeds"]) == DEFAULT_SEEDS:
            found[task, agent] = sweep_seconds(lines)
    return found


def timed_agent(task: str, agent: str, measured: Iterable[tuple[str, str]]) -> str:
    """The agent whose sweep on `task` stands for `agent`'s: proprio_baseline for an agent without images;
    multimodal_baseline for a baseline with images where `measured` has it on `task` (a baseline encodes one frame
    fewer a sample in an update); multimodal_bidal otherwise."""
    if not AGENTS[agent].uses_image:
        return "proprio_baseline"
    baseline = agent.endswith("_baseline") and (task, "multimodal_baseline") in measured
    return "multimodal_baseline" if baseline else "multimodal_bidal"


def epoch_time(task: str, agent: str, folder: str = EPOCH_SWEEPS) -> EpochTime | None:
    """The measured epoch of `agent` on `task` (`measured_epochs` of `folder`, `timed_agent`); where that is not
    measured, the same agent's on the task a labelled variant derives from (`envs_mjx.lineage`: nicol_lift_reduced
    as nicol_lift, nicol_slide_ee as nicol_slide: their physics, camera and presets); else (a new task) the longest
    measured epoch of the same agent on another task, else of any agent: an over-estimate. `estimated_plan` names
    both; None when nothing is measured."""
    measured = measured_epochs(folder)
    for base in envs_mjx.lineage(task):
        if (base, timed := timed_agent(base, agent, measured)) in measured:
            return EpochTime(*measured[base, timed], base)
    timed = timed_agent(task, agent, measured)
    same = [key for key in measured if key[1] == timed] or list(measured)
    if not same:
        return None
    longest = max(same, key=lambda key: measured[key][0])
    return EpochTime(*measured[longest], longest[0])


def estimate(arm: Arm, progress: Status) -> float:
    """Estimated seconds to train what is left of the run (`epoch_time`) at its `progress` (`status`): its
    compilation and its remaining epochs; 0 when it is done; all its epochs when it is stale (once its folder is
    moved away); NaN where nothing is measured."""
    state, step, _ = progress
    if state == "done":
        return 0.0
    timed = epoch_time(arm.given["env"], arm.given["agent"])
    if timed is None:
        return float("nan")
    per_epoch = timed.per_epoch * arm.config.run.seeds / DEFAULT_SEEDS  # 5 seeds measured; more cost in proportion
    return timed.compile + per_epoch * (arm.epochs - (0 if state == "stale" else step or 0))


def block_seeds(arm: Arm, limit: float = BLOCK_SECONDS) -> int:
    """The most of the arm's seeds that one run trains within `limit` seconds by `estimate` (at least one); all of
    them where nothing is measured."""
    timed = epoch_time(arm.given["env"], arm.given["agent"])
    if timed is None:
        return arm.config.run.seeds
    per_seed = timed.per_epoch / DEFAULT_SEEDS * arm.epochs
    return max(1, min(arm.config.run.seeds, int((limit - timed.compile) // per_seed)))


def blocks(arm: Arm, limit: float = BLOCK_SECONDS) -> list[Arm]:
    """The arm's seeds as runs that each end within `limit` seconds (`block_seeds`): the arm itself where they fit
    in one, else blocks of as even sizes as can be, each a run named NAME/seeds-A-B in RUN_DIR/seeds-A-B, A to B
    its seeds' indices in the arm, first seed `seed` + A (`report.load_run` merges them back into the arm's run)."""
    seeds = arm.config.run.seeds
    count = -(-seeds // block_seeds(arm, limit))
    if count == 1:
        return [arm]
    sizes = [seeds // count + (i < seeds % count) for i in range(count)]
    starts = [sum(sizes[:i]) for i in range(count)]
    first = arm.config.run.seed
    names = [report.block_name(a, a + n - 1) for a, n in zip(starts, sizes)]
    return [dataclasses.replace(arm, name=f"{arm.name}/{name}", given={
        **arm.given, "seeds": n, "seed": first + a, "run_dir": os.path.join(arm.run_dir, name)})
        for a, n, name in zip(starts, sizes, names)]


def duration(seconds: float) -> str:
    """Seconds, with minutes or hours: "300 s (5.0 min)", "8,720 s (2.4 h)"."""
    longer = f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.1f} min"
    return f"{seconds:,.0f} s ({longer})"


def estimated_plan(arms: Sequence[Arm], envs: dict[str, Any], heading: str = "plan:", named: bool = True) -> str:
    """`heading`, then one `plan_line` per run (after its name when `named`) with its estimated time (`estimate`),
    then the estimated total, the machine time the runs with epochs held, and the stale runs' count."""
    statuses = [status(arm, envs[arm.name].physics_id) for arm in arms]
    seconds = [estimate(arm, progress) for arm, progress in zip(arms, statuses)]
    lines = [heading]
    lines += [f"{f'{arm.name}: ' if named else ''}{plan_line(arm, envs[arm.name], progress)}"
              + ("" if math.isnan(s) else f"; estimated {s:,.0f} s")
              for arm, progress, s in zip(arms, statuses, seconds)]
    if math.isnan(sum(seconds)):
        lines.append(f"estimated time: unknown (no measured epochs in {EPOCH_SWEEPS})")
    else:
        lines.append(f"estimated time: {duration(sum(seconds))} on one GPU running the runs one after another "
                     "(an estimate from measured 5-seed programs of the default sizes, in proportion to the seeds, "
                     "compilation included)")
    timed = {arm.given["env"]: epoch_time(arm.given["env"], arm.given["agent"]) for arm in arms}
    borrowed: dict[str, list[str]] = {"the task it derives from": [], "the longest measured epoch": []}
    for task, t in timed.items():
        if t is not None and t.task != task:
            which = "the task it derives from" if t.task in envs_mjx.lineage(task) else "the longest measured epoch"
            borrowed[which].append(f"{task} as {t.task}")
    lines += [f"not measured in results/scaling/epochs, estimated as {which}: {', '.join(named)}"
              for which, named in borrowed.items() if named]
    done = [run for arm in arms if (run := loaded(arm.run_dir))]
    if done:
        held, summed = report.machine_time(done)
        lines.append(f"held so far: {duration(held)} of GPU time by the {len(done)} runs with epochs (wall time × the "
                     "GPUs of their machine, runs that shared a GPU counted once as results/*/figures.json records "
                     f"them: `report.machine_time`); their summed process time {duration(summed)}")
    stale_runs = sum(progress.state == "stale" for progress in statuses)
    if stale_runs:
        lines.append(f"stale: {stale_runs} of {len(arms)} runs; training refuses them until their folders are moved "
                     "away or another --out is given (the estimate counts them from the start)")
    return "\n".join(lines)


def without_buffer(arm: Arm) -> bool:
    """Whether the run's latest checkpoint lacks its replay buffer: training resumes it only with `--fresh-buffer`,
    with an empty buffer, as `experiments.run --resume --fresh-buffer` does."""
    directory = os.path.join(arm.run_dir, "checkpoints")
    return checkpoint.latest_step(directory) is not None and not checkpoint.has_buffer(directory)


def train_arm(arm: Arm, env, quiet: bool, fresh_buffer: bool = False) -> None:
    """Train one run to its epochs (resuming its latest checkpoint with its replay buffer), or skip it when done.
    A checkpoint without its buffer is refused (CheckpointError) unless `fresh_buffer` resumes it with an empty
    one. Stale runs are refused before, by `train_arms`, for all its arms at once."""
    state = status_at(latest(arm), arm.epochs)
    if state == "done":
        print(f"{arm.name}: done ({arm.run_dir}): its {arm.epochs} epochs finished, skipped")
        return
    resume = state == "resume"  # else a run stopped before its first checkpoint starts again
    empty = resume and without_buffer(arm)
    if empty and not fresh_buffer:
        raise CheckpointError(f"{arm.run_dir}: its latest checkpoint has no replay buffer; --fresh-buffer resumes "
                              "it with an empty one (a deviation from the uninterrupted run, named below the table)")
    if empty:
        print(f"{arm.name}: its checkpoint has no replay buffer: resuming with an empty one (--fresh-buffer; "
              "recorded in its config.json, named below the table)")
    config, row = cli.start_run(arm.given, resume=resume, overwrite=not resume, quiet=quiet, env=env,
                                initialize=arm.initialize, fresh_buffer=empty)
    print(f"{arm.name}:", end=" ")
    cli.print_summary(config.run, row)


def train_cell(payload: tuple[Arm, bool]) -> tuple[int, str | None]:
    """A Ray task's run (`cluster.run_cells`): `train_arm` of the arm in `payload` (with its `fresh_buffer`) on an
    env built in the worker, without progress bars (the driver prints the grid's table); its exit code and, when
    it failed, its one line (`cli.failure`), which the driver reports."""
    arm, fresh_buffer = payload
    try:
        memory.share_gpu()  # before the env puts its model on the GPU: JAX takes what is free of a shared GPU
        train_arm(arm, envs_mjx.make(arm.given["env"], render=arm.config.agent.uses_image), True, fresh_buffer)
    except cli.FAILURES as err:
        return cli.failure(err)
    return 0, None


def train_arms(arms: Sequence[Arm], envs: dict[str, Any], args: argparse.Namespace, out: str) -> int:
    """Train the runs (`args`: an experiment's `quiet`, `add_training_options`) of the experiment in the folder `out`;
    the exit code. A stale run among them (`refuse_stale`) is refused before any trains: 2. Without `--ray`, in
    order in this process (`train_arm`) until one fails or is stopped; with it, each a cell of `cluster.run_cells`,
    all at once where the machine or cluster has room, an arm after those of `arms` it names in `after`, `out`
    held by the grid (a second grid on it is refused: 2)."""
    try:
        refuse_stale(arms, envs)
        if cluster.wanted(args):
            cells = [cluster.Cell(arm.name, arm.epochs, (arm, args.fresh_buffer),
                                  functools.partial(cluster.epochs_done, arm.run_dir), arm.after) for arm in arms]
            return cluster.run_cells(cells, train_cell, args, out)
        for arm in arms:
            train_arm(arm, envs[arm.name], args.quiet, args.fresh_buffer)
    except cli.FAILURES as err:
        return cli.exit_code(err)
    return 0


def fresh_buffer_note(configs: dict[str, dict]) -> list[str]:
    """The lines below a table naming its runs resumed with an empty replay buffer (`--resume --fresh-buffer`:
    config.json's "fresh_buffer_epochs"), `configs` name -> config.json; none when no run was."""
    resumed = [f"{name} after epoch{'s' * (len(epochs) > 1)} {', '.join(map(str, epochs))}"
               for name, config in configs.items() if (epochs := config.get("fresh_buffer_epochs"))]
    if not resumed:
        return []
    return [
        f"Resumed on another machine with an empty replay buffer (`--resume --fresh-buffer`, a deviation from an "
        f"uninterrupted run: the next epochs learn from fresh episodes only): {'; '.join(resumed)}.",
        "",
    ]


def unfinished(arms: Sequence[Arm], runs: dict[str, dict]) -> list[Arm]:
    """The arms whose runs (`runs`: name -> `loaded` run) have epochs, but fewer than the arm's."""
    return [arm for arm in arms if arm.name in runs and runs[arm.name]["epoch"][-1] < arm.epochs]


def gaps(arms: Sequence[Arm], runs: dict[str, dict]) -> str:
    """The line naming the runs without epochs, those short of their epochs, and those whose metrics.csv
    lacks rows (their final success averages their last rows, whatever epochs those are)."""
    missing = [arm.name for arm in arms if arm.name not in runs]
    unfinished_runs = [f"{arm.name} (epoch {int(runs[arm.name]['epoch'][-1])} of {arm.epochs})"
                       for arm in unfinished(arms, runs)]
    absent = report.absent_note({arm.name: runs[arm.name]["epoch"] for arm in arms if arm.name in runs})
    absent_line = f" {absent}" if absent else ""
    if not missing and not unfinished_runs:
        return "No run is missing or unfinished." + absent_line
    return f"Missing: {', '.join(missing) or 'none'}. Unfinished: {', '.join(unfinished_runs) or 'none'}." \
        + absent_line


def write_table(out: str, text: str | None) -> None:
    """Write `text` to OUT/table.md (`runfiles.write_atomic`; a failed write is one line, `rundir.writing`) and print
    it; None: no run has epochs yet."""
    if text is None:
        print("no epochs yet: nothing to plot")
        return
    path = os.path.join(out, "table.md")
    with rundir.writing(path):
        runfiles.write_atomic(path, text)
    print(f"\n{text}\nwritten to {out}")


def write_figure(curves: Sequence[report.Curve], prefix: str, title: str) -> None:
    """`report.plot` into PREFIX.png and PREFIX.csv, a failed write one line (`rundir.writing`)."""
    with rundir.writing(f"{prefix}.png and {prefix}.csv"):
        report.plot(curves, prefix, title=title)
