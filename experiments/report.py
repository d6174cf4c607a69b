"""Reports of training runs, shared by the commands: reading runs, curves, tables and plots.

- `load_run(run_dir)`: a run directory's `config.json` and `metrics.csv` as arrays, read through
  `bidal_jax.run.runfiles` (the one reader of run files): `NotARun` for a folder without a run with epochs,
  `RunError` naming the file for a damaged one. A folder of seed blocks (`seeds-A-B/`, runs of a grid cell's
  seeds A to B, `experiments.paper.grid.blocks`) reads as one run of all their seeds (`merge_blocks`).
- `curves(runs, label_by, labels, panel_by)`: one `Curve` per run (per-seed eval success
  against epochs, env steps and wall time), labelled and grouped into panels.
- `final_per_seed`, `final_success`, `final_cell`, `time_to_threshold`, `normalized_auc`: a curve's figures
  (the paper's "success rate over the last N epochs", Table II).
- `absent_epochs`, `absent_note`: the epochs a run reached that its metrics.csv has no row for (rows lost
  outside the run), and the sentence the tables name them in.
- `plot(curves, prefix)`: PREFIX.png (one panel per env or `panel_by` value, the seed mean
  with a band of ± one standard deviation over seeds: numpy's population std, 0 for one
  seed) and PREFIX.csv (the plotted numbers).
- `markdown_table`, `summary_table`: Markdown tables.
- `load_floors`: each task's floor (what a policy that does nothing scores, per goal subset), as
  `python -m experiments.probes.floors` stored it in results/floors/figures.json; `floor_text` names it beside a
  score, `seeds_above` tests each seed's last epochs against it.
- `machine_time`: the GPU time runs held, runs that shared a GPU counted once (`gpu_sharing`).

Times: metrics.csv's `wall_time` counts from when the training programs were built (compilation
not counted), `wall_time_with_compile` from when training began (compilation included; absent
from runs recorded before it); `last_time(run)` gives the tables the latter where a run has it.

Used by `python -m experiments.plot`, the paper experiments and the benchmarks. It imports
neither JAX nor the environments (matplotlib only when it draws), so that it stays light; the commands
that call it map the failures of its writes to one line (`bidal_jax.run.rundir.writing`).
"""

from __future__ import annotations

import csv
import dataclasses
import fnmatch
import functools
import glob
import json
import os
import re
import subprocess
from collections import Counter
from typing import Callable, Mapping, Sequence

import numpy as np

from bidal_jax.run import runfiles
from experiments import stats

X_AXES = {"env_steps": "env steps per seed", "epoch": "epoch", "wall_time": "wall time (s)"}
SEED_COLUMN = re.compile(r"eval_success_seed(\d+)$")
BLOCK = re.compile(r"seeds-(\d+)-(\d+)$")  # a block's folder in its cell's: the indices of its first and last seed
AIR = "eval_success_air"  # nicol_lift's success over its air goals alone (`Env.goal_subsets`)
WITH_COMPILE = "wall_time_with_compile"
ENGINES = {"jax": "MJX-JAX", "warp": "MuJoCo Warp"}  # a run's physics engine (config.json's physics_engine) by name
NOT_RECORDED = "not recorded"


def checkout_commit() -> str:
    """The short hash of this checkout's HEAD, with " + changes" where tracked files differ from it, for a results
    record; `NOT_RECORDED` outside a git checkout or without git."""
    here = os.path.dirname(os.path.abspath(__file__))

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", here, *args], capture_output=True, text=True, timeout=10).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        changed = bool(head) and bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return NOT_RECORDED
    return head + " + changes" * changed if head else NOT_RECORDED
FLOORS = os.path.join("results", "floors")  # where `python -m experiments.probes.floors` writes the floors
FLOORS_FILE = "figures.json"
ALPHA = 0.05  # the level of the per-seed test against the floor (`seeds_above`)


class RunError(runfiles.RunFileError):
    """A run directory that cannot be read (a damaged file in it); the message is one line naming its path."""


class NotARun(RunError):
    """A folder without a run with epochs (yet): missing, without config.json or metrics.csv, or no row."""


def _column(path: str, rows: list[dict[str, str]], name: str) -> np.ndarray:
    return np.array([runfiles.number(path, r, name) for r in rows])


def _read(run_dir: str, config_path: str, metrics_path: str) -> tuple[dict, list[dict[str, str]]]:
    """(config.json, metrics.csv's whole rows) of a run directory; NotARun or RunError naming the path."""
    if not os.path.isdir(run_dir):
        raise NotARun(f"{run_dir}: no such run directory")
    for path in (config_path, metrics_path):
        if not os.path.lexists(path):
            raise NotARun(f"{run_dir}: not a run directory (no {os.path.basename(path)})")
    try:
        return runfiles.read_json(config_path), runfiles.read_csv(metrics_path)[1]  # a row cut short is no epoch
    except runfiles.RunFileError as err:
        raise RunError(str(err)) from None


def block_name(first: int, last: int) -> str:
    """The folder of the block of a cell's seeds `first` to `last` (indices in the cell), matched by `BLOCK`."""
    return f"seeds-{first}-{last}"


def block_dirs(run_dir: str) -> list[str]:
    """The seed blocks in `run_dir` (`BLOCK`), by their first seed; [] where there are none."""
    found = [(int(m.group(1)), name) for name in os.listdir(run_dir) if (m := BLOCK.match(name))] \
        if os.path.isdir(run_dir) else []
    return [os.path.join(run_dir, name) for _, name in sorted(found)]


def merge_blocks(run_dir: str, blocks: Sequence[dict], planned: int = 0) -> dict:
    """One run of the seeds of `blocks` (`load_run`s of one cell, in seed order) over the epochs they all reached:
    its seeds side by side, its times summed over the blocks (GPU time), its config the first block's with their
    seeds counted together, and "planned_seeds" the cell's seeds by its block folders (`planned`, at least those
    merged), so that a block without epochs yet leaves the run short rather than smaller. RunError where the blocks
    are not of one task, agent and epoch size."""
    first = blocks[0]
    for block in blocks[1:]:
        if (block["env"], block["agent"]) != (first["env"], first["agent"]):
            raise RunError(f"{block['dir']}: a block of {block['env']} {block['agent']} beside "
                           f"{first['env']} {first['agent']} in {run_dir}")
    epochs = min(len(b["epoch"]) for b in blocks)
    steps = first["env_steps"][:epochs]
    for block in blocks:
        if not np.allclose(block["env_steps"][:epochs], steps):
            raise RunError(f"{block['dir']}: its env steps per epoch differ from those of {first['dir']}")

    def joined(key: str, combine: Callable) -> np.ndarray | None:
        parts = [b[key] for b in blocks]
        return None if any(p is None for p in parts) else combine([p[:epochs] for p in parts])

    seeds = sum(b["seeds"] for b in blocks)
    config = {**first["config"], "run": {**first["config"]["run"], "seeds": seeds},
              "blocks": [os.path.basename(b["dir"]) for b in blocks]}
    summed = functools.partial(np.sum, axis=0)
    return {
        "dir": run_dir, "name": os.path.basename(os.path.normpath(run_dir)), "config": config, "env": first["env"],
        "agent": first["agent"], "seeds": seeds, "planned_seeds": max(planned, seeds), "epoch": first["epoch"][:epochs],
        "env_steps": steps,
        "wall_time": joined("wall_time", summed), WITH_COMPILE: joined(WITH_COMPILE, summed),
        "success": joined("success", functools.partial(np.concatenate, axis=1)),
        "success_air": joined("success_air", functools.partial(np.concatenate, axis=1)),
    }


def load_run(run_dir: str) -> dict:
    """One run: its config, env, agent, seeds and per-epoch arrays.

    Keys: "dir", "name" (basename), "config" (the parsed config.json; `physics_of` reads its physics), "env", "agent",
    "seeds", "planned_seeds" (more than "seeds" where blocks of a cell's seeds have no epochs yet), "epoch" [E],
    "env_steps" [E] (per seed: env_steps_total / seeds), "wall_time" [E],
    "wall_time_with_compile" [E] (None where metrics.csv predates it), "success" [E, S] (eval
    success of each seed), "success_air" [E, S] (each seed's success over air goals, `AIR`; None for a task
    without them or a run older than that column). Raises NotARun (a folder without a run with epochs yet) or
    RunError (a damaged file), naming the path.
    """
    config_path, metrics_path = os.path.join(run_dir, "config.json"), os.path.join(run_dir, "metrics.csv")
    if not os.path.lexists(config_path) and (blocks := block_dirs(run_dir)):
        found = [run for run in map(loaded, blocks) if run is not None]
        if not found:
            raise NotARun(f"{run_dir}: no block of its seeds has epochs yet")
        return merge_blocks(run_dir, found, max(int(BLOCK.match(os.path.basename(b)).group(2)) + 1 for b in blocks))
    config, rows = _read(run_dir, config_path, metrics_path)
    try:
        env, agent, seeds = config["run"]["env"], config["run"]["agent"], int(config["run"]["seeds"])
    except (ValueError, KeyError, TypeError) as err:
        raise RunError(f"{config_path}: unreadable run config ({err!r})") from err
    if not rows:
        raise NotARun(f"{metrics_path}: no epochs yet")
    seed_columns = sorted((int(m.group(1)), k) for k in rows[0] if (m := SEED_COLUMN.match(k)))
    if [i for i, _ in seed_columns] != list(range(seeds)):
        raise RunError(f"{metrics_path}: expected columns eval_success_seed0..{seeds - 1} for {seeds} seeds")
    try:
        success = np.stack([_column(metrics_path, rows, k) for _, k in seed_columns], axis=1)
        epoch, wall = _column(metrics_path, rows, "epoch"), _column(metrics_path, rows, "wall_time")
        with_compile = _column(metrics_path, rows, WITH_COMPILE) if WITH_COMPILE in rows[0] else None
        steps = _column(metrics_path, rows, "env_steps_total") / seeds
        air_columns = [f"{AIR}_seed{i}" for i in range(seeds)]
        air = np.stack([_column(metrics_path, rows, k) for k in air_columns], axis=1) \
            if all(k in rows[0] for k in air_columns) else None
    except runfiles.RunFileError as err:
        raise RunError(str(err)) from None
    return {
        "dir": run_dir, "name": os.path.basename(os.path.normpath(run_dir)), "config": config, "env": env,
        "agent": agent, "seeds": seeds, "planned_seeds": seeds, "epoch": epoch, "env_steps": steps, "wall_time": wall,
        WITH_COMPILE: with_compile, "success": success, "success_air": air,
    }


def loaded(run_dir: str) -> dict | None:
    """The run's metrics and config (`load_run`), or None while it has no epochs (`NotARun`); a damaged file raises
    `RunError` naming it: an experiment stops on it (exit 2) rather than take the run for one never trained."""
    try:
        return load_run(run_dir)
    except NotARun:
        return None


def physics_of(config: dict) -> list[str]:
    """The physics fingerprints a run's config.json records (`bidal_jax.run.loop.history_record`); [] if none."""
    physics = config.get("physics")
    return [str(p) for p in physics] if isinstance(physics, list) else []


def last_time(run: dict) -> tuple[float, bool]:
    """(The run's last time, whether it counts its compilation): its last `wall_time_with_compile`, or its last
    `wall_time` (its times start after compiling) where metrics.csv predates that column."""
    if run[WITH_COMPILE] is None:
        return float(run["wall_time"][-1]), False
    return float(run[WITH_COMPILE][-1]), True


@dataclasses.dataclass(frozen=True)
class Curve:
    """One line of the plot: a run's per-seed success [E, S] with its x axes [E]."""

    panel: str
    label: str
    run_dir: str
    epoch: np.ndarray
    env_steps: np.ndarray
    wall_time: np.ndarray
    success: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        return self.success.mean(axis=1)

    def first(self, epochs: int) -> "Curve":
        """The curve over its first `epochs` epochs (all of them where it has fewer): arms compared over the same
        budget."""
        return dataclasses.replace(self, epoch=self.epoch[:epochs], env_steps=self.env_steps[:epochs],
                                   wall_time=self.wall_time[:epochs], success=self.success[:epochs])

    @property
    def std(self) -> np.ndarray:
        return self.success.std(axis=1)

    @property
    def n_seeds(self) -> int:
        return self.success.shape[1]


Label = str | Callable[[dict], str]


def label_of(run: dict, by: Label) -> str:
    """A run's label (or panel): a callable's value, or by key: "agent", "run" (basename), "env",
    or a config value "GROUP.FIELD" (e.g. "train.intrinsic_lambda" -> "intrinsic_lambda=0.1")."""
    if callable(by):
        return by(run)
    if by == "run":
        return run["name"]
    if by in ("agent", "env"):
        return run[by]
    group, _, field = by.partition(".")
    if field not in run["config"].get(group, {}):
        raise ValueError(f"{by}: not agent, run, env or a config key GROUP.FIELD of {run['dir']}")
    return f"{field}={run['config'][group][field]}"


def curves(
    runs: Sequence[dict], label_by: Label = "agent", labels: Mapping[str, str] | None = None, panel_by: Label = "env"
) -> list[Curve]:
    """One curve per run, in the order given, in panels by `panel_by` (see `label_of`; e.g.
    "train.<noise field>" for the noise experiment's one panel per κ).

    `labels` maps run directories to names and overrides `label_by`. Runs of one panel that get
    the same label from `label_by` are labelled by their basenames instead; a label still
    shared in a panel (e.g. given twice in `labels`) is a ValueError.
    """
    overrides = {os.path.normpath(k): v for k, v in (labels or {}).items()}
    unknown = set(overrides) - {os.path.normpath(r["dir"]) for r in runs}
    if unknown:
        raise ValueError(f"--label {sorted(unknown)[0]}: not one of the run directories given")
    panels = [label_of(r, panel_by) for r in runs]
    names = [label_of(r, label_by) for r in runs]
    shared = Counter(zip(panels, names))
    names = [r["name"] if shared[p, n] > 1 else n for r, p, n in zip(runs, panels, names)]
    names = [overrides.get(os.path.normpath(r["dir"]), n) for r, n in zip(runs, names)]
    clash = next((key for key, count in Counter(zip(panels, names)).items() if count > 1), None)
    if clash:
        raise ValueError(f"two runs in panel {clash[0]} are labelled {clash[1]!r}: name them with --label RUN_DIR=NAME")
    return [
        Curve(p, n, r["dir"], r["epoch"], r["env_steps"], r["wall_time"], r["success"])
        for r, p, n in zip(runs, panels, names)
    ]


def absent_epochs(epochs: Sequence[float]) -> list[int]:
    """The epochs from 1 to the last of a run's `epochs` (its metrics.csv rows) that have no row: rows lost
    outside the run (a file damaged or replaced while the run trained), not epochs it skipped."""
    return sorted(set(range(1, int(epochs[-1]) + 1)) - {int(e) for e in epochs})


def epoch_spans(epochs: Sequence[int]) -> str:
    """Sorted epochs as spans: [1, 2, 3, 5] -> "1-3, 5"."""
    spans: list[list[int]] = []
    for e in epochs:
        if spans and e == spans[-1][1] + 1:
            spans[-1][1] = e
        else:
            spans.append([e, e])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)


def absent_note(named: Mapping[str, Sequence[float]]) -> str:
    """The sentence naming each run (name -> its metrics.csv epochs) that lacks rows, with the epochs as spans
    ("1-58; 91"); empty when none does."""
    holes = [f"{name} ({epoch_spans(absent)})" for name, epochs in named.items() if (absent := absent_epochs(epochs))]
    if not holes:
        return ""
    return (f"Epochs without a row in metrics.csv: {'; '.join(holes)}; the final success averages the last rows "
            "there are.")


def final_per_seed(curve: Curve, last_n: int) -> np.ndarray:
    """Each seed's mean success over its last min(last_n, E) epochs [S]."""
    return curve.success[-last_n:].mean(axis=0)


def final_success(curve: Curve, last_n: int) -> tuple[float, float, int]:
    """(mean, std over seeds, epochs used) of each seed's mean success over its last
    min(last_n, E) epochs: the paper's "success rate over the last N epochs" (Table II)."""
    per_seed = final_per_seed(curve, last_n)
    return float(per_seed.mean()), float(per_seed.std()), min(last_n, len(curve.epoch))


@dataclasses.dataclass(frozen=True)
class Reached:
    """Where a curve first reached a threshold: its epoch, env steps per seed and wall time."""

    epoch: int
    env_steps: float
    wall_time: float


def time_to_threshold(curve: Curve, threshold: float) -> Reached | None:
    """The first epoch whose seed-mean success is ≥ threshold, or None if none is."""
    hits = np.flatnonzero(curve.mean >= threshold)
    if not hits.size:
        return None
    i = hits[0]
    return Reached(int(curve.epoch[i]), float(curve.env_steps[i]), float(curve.wall_time[i]))


def normalized_auc(curve: Curve) -> float:
    """Area under the seed-mean success curve over epochs, divided by their number (in [0, 1])."""
    return float(curve.mean.mean())


def write_csv(cs: Sequence[Curve], path: str, x: str = "env_steps") -> None:
    """The plotted numbers, one row per curve and epoch: panel, label, x, mean, std, n_seeds."""
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["panel", "label", "x", "mean", "std", "n_seeds"])
        for c in cs:
            for xv, m, s in zip(getattr(c, x), c.mean, c.std):
                writer.writerow([c.panel, c.label, float(xv), float(m), float(s), c.n_seeds])


def plot(cs: Sequence[Curve], prefix: str, x: str = "env_steps", title: str = "") -> tuple[str, str]:
    """Draw `cs` (one axes per panel, a colour per label across panels) into PREFIX.png and
    write PREFIX.csv; returns both paths. Uses the Agg canvas, leaving pyplot's backend alone."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import EngFormatter

    if x not in X_AXES:
        raise ValueError(f"--x {x}: must be one of {', '.join(X_AXES)}")
    panels = list(dict.fromkeys(c.panel for c in cs))
    colours = {label: f"C{i % 10}" for i, label in enumerate(dict.fromkeys(c.label for c in cs))}
    fig = Figure(figsize=(4.5 * len(panels), 3.6), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels):
        for c in (c for c in cs if c.panel == panel):
            xs = getattr(c, x)
            seeds = f"{c.n_seeds} seed" + ("s" if c.n_seeds > 1 else "")
            ax.plot(xs, c.mean, color=colours[c.label], label=f"{c.label} ({seeds})")
            ax.fill_between(xs, c.mean - c.std, c.mean + c.std, color=colours[c.label], alpha=0.2, linewidth=0)
        ax.set(title=panel, xlabel=X_AXES[x], ylabel="eval success", ylim=(-0.02, 1.02))
        if x == "env_steps":
            ax.xaxis.set_major_formatter(EngFormatter(sep=""))  # 20k, 1.5M
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    if title:
        fig.suptitle(title)
    png, table = f"{prefix}.png", f"{prefix}.csv"
    fig.savefig(png, dpi=120)
    write_csv(cs, table, x)
    return png, table


def markdown_table(head: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A Markdown table: the header `head`, its rule, then one line per row of cells."""
    lines = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(cells) + " |" for cells in rows])


def final_cell(curve: Curve, last_n: int) -> str:
    """`final_success` as "mean ± std", with "(last k)" when the curve has fewer than `last_n` epochs."""
    mean, std, used = final_success(curve, last_n)
    return f"{mean:.3f} ± {std:.3f}" + ("" if used == last_n else f" (last {used})")


def summary_table(
    runs: Sequence[dict], last_n: int, label_by: Label = "agent", labels: Mapping[str, str] | None = None,
    threshold: float | None = None, panel_by: Label = "env",
) -> str:
    """Markdown: per curve (`curves`), final success mean ± std over seeds (`final_success`), the
    normalised AUC, and with `threshold` the epoch, env steps per seed and time it was reached."""
    panel = panel_by if isinstance(panel_by, str) else "panel"
    head = [panel, "label", "seeds", "epochs", f"success, last {last_n} epochs (mean ± std over seeds)", "AUC"]
    if threshold is not None:
        head.append(f"first mean ≥ {threshold:g}: epoch, env steps per seed, time")
    rows = []
    for c in curves(runs, label_by, labels, panel_by):
        cells = [c.panel, c.label, str(c.n_seeds), str(len(c.epoch)), final_cell(c, last_n), f"{normalized_auc(c):.3f}"]
        if threshold is not None:
            hit = time_to_threshold(c, threshold)
            cells.append("never" if hit is None else f"{hit.epoch}, {hit.env_steps:,.0f}, {hit.wall_time:.0f} s")
        rows.append(cells)
    return markdown_table(head, rows)


@dataclasses.dataclass(frozen=True)
class Floor:
    """A task's floor over one goal subset: the estimate, its 95 % Monte Carlo half-width and the share of goals in
    the subset (`envs_mjx.floors`)."""

    value: float
    half_width: float
    share: float

    @property
    def bound(self) -> float:
        """What a seed is tested against (`seeds_above`): the estimate's upper 95 % bound, so that the floor's Monte
        Carlo error cannot make a seed at the floor look above it."""
        return self.value + self.half_width


Floors = dict[str, dict[str, Floor]]  # task -> goal subset ("all", "air", "table") -> its floor


def load_floors(folder: str = FLOORS) -> Floors:
    """The floors stored in FOLDER/figures.json (`experiments.probes.floors`): task -> subset -> `Floor`; {} where
    the file does not exist (the tables then say the floor is not computed); RunError naming a damaged one."""
    path = os.path.join(folder, FLOORS_FILE)
    if not os.path.exists(path):
        return {}
    try:
        with open(path, encoding="utf-8") as f:
            found = json.load(f)
        return {task: {name: Floor(float(f["value"]), float(f["half_width"]),
                                   f["resets"] / subsets["all"]["resets"]) for name, f in subsets.items()}
                for section in found if "floors" in section for task, subsets in section["floors"].items()}
    except (OSError, KeyError, TypeError, ValueError, ZeroDivisionError) as err:  # a bad JSON is a ValueError
        raise RunError(f"{path}: not the floors `python -m experiments.probes.floors` writes ({err!r})") from None


def floor_value(floors: Floors, task: str, subset: str = "all") -> str:
    """"0.031" for a task's floor over `subset`; "not computed" where results/floors lacks it."""
    found = floors.get(task, {}).get(subset)
    return "not computed" if found is None else f"{found.value:.3f}"


def floor_text(floors: Floors, task: str, subset: str = "all") -> str:
    """"floor 0.031" (`floor_value`)."""
    return f"floor {floor_value(floors, task, subset)}"


def seeds_above(success: np.ndarray, episodes: float, floor: float, last_n: int, alpha: float = ALPHA) -> np.ndarray:
    """Per seed [S] of `success` [E, S] (eval success per epoch), whether it is clearly above `floor`: the one-sided
    binomial test (`stats.above_p`) of its successes among its last min(last_n, E) epochs' eval episodes
    (`episodes` an epoch per seed: the run's eval_envs, times the share of goals in a subset for a subset's
    success, rounded down) against `floor`, Holm-corrected over the seeds (`stats.holm`), at `alpha`."""
    per_epoch = int(episodes)
    window = success[-last_n:]
    hits = np.rint(window * per_epoch).sum(axis=0).astype(int)
    p = [stats.above_p(int(k), per_epoch * window.shape[0], floor) for k in hits]
    return stats.holm(p) < alpha


RESULTS = "results"  # the experiments' results folder, whose figures.json files record how their runs shared GPUs


def gpu_sharing(root: str = RESULTS) -> list[tuple[tuple[str, ...], int]]:
    """How runs shared a GPU, as each experiment's figures.json records it (ROOT/*/figures.json, a section's
    "gpu_sharing": [{"runs": [glob patterns of run folders relative to ROOT], "at_once": k}, ...]): (patterns, k)
    per group of runs that trained k at a time on one machine. config.json and metrics.csv record neither when a
    run started nor what ran beside it, so this is the record the machine time rests on."""
    groups = []
    for path in sorted(glob.glob(os.path.join(root, "*", "figures.json"))):
        with open(path, encoding="utf-8") as f:
            sections = json.load(f)
        groups += [(tuple(g["runs"]), int(g["at_once"])) for s in sections for g in s.get("gpu_sharing", [])]
    return groups


def gpus_of(run: dict) -> int:
    """The GPUs of the machine a run's processes ran on: the most of config.json's "hardware" entries ("2 × <GPU
    name> ..."); 1 where it records none."""
    counts = [int(m.group(1)) for h in run["config"].get("hardware") or [] if (m := re.match(r"(\d+) ×", h))]
    return max(counts, default=1)


def machine_time(runs: Sequence[dict], root: str = RESULTS,
                 groups: Sequence[tuple[tuple[str, ...], int]] | None = None) -> tuple[float, float]:
    """(Machine seconds, process seconds) of `runs`: process time is the sum of each run's `last_time`; machine
    time is the time the GPUs were held, wall time × the GPUs of the machine (`gpus_of`), with runs that shared a
    machine counted once: a group of runs that trained k at a time (`gpu_sharing`, by their folders relative to
    `root`) held it for max(their summed time / k, the longest of them), a queue that keeps k running; a run in no
    group held its machine alone."""
    return sum(machine_shares(runs, root, groups).values()), sum(last_time(run)[0] for run in runs)


def machine_shares(runs: Sequence[dict], root: str = RESULTS,
                   groups: Sequence[tuple[tuple[str, ...], int]] | None = None) -> dict[str, float]:
    """Each run's folder -> its part of `machine_time(runs)`: a run in no group its own, a group's time shared by its
    members in proportion to their times. The parts of any subset of `runs` add up to what they held as members of
    `runs`: a group split between experiments is counted once over them, not once in each."""
    groups = gpu_sharing(root) if groups is None else groups
    members: dict[int, list[dict]] = {}
    shares = {}
    for run in runs:
        where = os.path.relpath(run["dir"], root)
        found = next((i for i, (patterns, _) in enumerate(groups) if any(fnmatch.fnmatch(where, p) for p in patterns)),
                     None)
        if found is None:
            shares[run["dir"]] = last_time(run)[0] * gpus_of(run)
        else:
            members.setdefault(found, []).append(run)
    for i, shared in members.items():
        times = [last_time(run)[0] for run in shared]
        held = max(sum(times) / groups[i][1], max(times)) * max(gpus_of(run) for run in shared)
        shares.update({run["dir"]: held * t / max(sum(times), 1e-12) for run, t in zip(shared, times)})
    return shares
