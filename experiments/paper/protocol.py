"""The paper's protocol (Sec. IV): what its experiments run and how their figures are measured.

Shared by the experiments that train the runs (`curves`, `noise_robustness`, `transfer_learning`)
and `claims`, which measures the paper's claims from their run folders:

- the learning curves (Fig. 4): the tasks and their epoch budgets, the same for every agent, which each task
  declares (`paper_epochs`: the registered envs' `task.paper_epochs`, envs_mjx/task.py);
- noise robustness (Table II): `KAPPAS`, the window `LAST_N` per κ, `NOISE_AGENTS`, the noised
  `SEGMENTS`, the paper's figures `PAPER`; `kappa_curves` splits a run of 3 κ × R vmapped runs by
  κ (`kappa_dir` names the folder of one κ's runs alone), `residual_spread` is each run's std around its
  fitted trend over its last N epochs and `trending` says whether the runs still climb there,
  `load_noise_curves` reads them all;
- transfer (Fig. 6): `SOURCE_ENV`, `TARGET_ENV`, `AGENT` and `THRESHOLDS`; `seed_measures` gives
  each seed's AUC and env steps to each threshold.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import chex
import numpy as np

import envs_mjx
from experiments import cli, report, stats


# ----- learning curves (Fig. 4) ---------------------------------------------------------------
def paper_epochs() -> dict[str, int]:
    """The learning curves' tasks and budgets (experiments.paper.curves), in the registry's order: each registered
    task that declares one (its env's `task.paper_epochs`: where the slowest agent that learns the task levels off in
    pilot runs, plus a margin; docs/deviations.md, "Learning-curve budgets"), the same for every agent of the task."""
    budgets = {name: envs_mjx.task(name).paper_epochs for name in envs_mjx.names()}
    return {name: epochs for name, epochs in budgets.items() if epochs is not None}


def paper_tasks() -> tuple[str, ...]:
    """The learning curves' tasks (`paper_epochs`), in the registry's order."""
    return tuple(paper_epochs())


# seeds per cell of the grid (a task and an agent), trained in blocks that each finish in `BLOCK_SECONDS`
# (`grid.blocks`)
DEFAULT_SEEDS = 5
DEFAULT_SEED = 0  # the first random seed of every run (the experiments' --seed)
# a block of a cell's seeds is one run estimated to end within this, compilation included, on one GPU: GPUs
# held for half an hour, cluster jobs with wall-time limits and preemptible machines lose at most one block
BLOCK_SECONDS = 1200.0

LIFTS = 0.5  # a seed lifts when its success over air goals over the last epochs is at least this


def seeds_that_lift(final_air: np.ndarray) -> int:
    """How many seeds lift, of their final success over air goals [S] (each seed's mean over its last epochs):
    those at `LIFTS` or more."""
    chex.assert_rank(final_air, 1)
    return int((final_air >= LIFTS).sum())


# ----- noise robustness (Table II) --------------------------------------------------------------
KAPPAS = (0.05, 0.10, 0.15)
# the noise runs' epochs: the widest window (30 epochs) after nicol_slide's level-off (epoch 10-13) and a margin
NOISE_EPOCHS = 45
LAST_N = {0.05: 5, 0.10: 30, 0.15: 30}  # the paper's window per κ (Table II)
NOISE_AGENTS = ("multimodal_bidal", "multimodal_baseline", "proprio_baseline")
NOISE_ENV = "nicol_slide"
SEGMENTS = "ee_pos,ee_rot,obj_pos"
# the paper's Table II: κ -> agent -> (mean, std)
PAPER = {
    0.05: {"multimodal_bidal": (0.874, 0.0127), "multimodal_baseline": (0.886, 0.0143),
           "proprio_baseline": (0.882, 0.0191)},
    0.10: {"multimodal_bidal": (0.764, 0.0222), "multimodal_baseline": (0.696, 0.0542),
           "proprio_baseline": (0.699, 0.0519)},
    0.15: {"multimodal_bidal": (0.615, 0.0320), "multimodal_baseline": (0.590, 0.0410),
           "proprio_baseline": (0.554, 0.0358)},
}


def kappa_dir(agent: str, kappa: float) -> str:
    """The folder of one agent's runs at one κ alone (`noise_robustness --kappas`), e.g. proprio_baseline-kappa10."""
    return f"{agent}-kappa{round(kappa * 100):02d}"


def kappa_curve(run: dict, kappa: float, seeds: slice = slice(None)) -> report.Curve:
    """The curve of the run's `seeds` (all by default), all trained at `kappa`."""
    return report.Curve(f"κ = {kappa:.0%}", run["agent"], run["dir"], run["epoch"], run["env_steps"],
                        run["wall_time"], run["success"][:, seeds])


def kappa_curves(run: dict, runs: int) -> list[report.Curve]:
    """The run's curve split by κ: one curve per κ over its `runs` seeds."""
    return [kappa_curve(run, k, slice(i * runs, (i + 1) * runs)) for i, k in enumerate(KAPPAS)]


def window_fit(curve: report.Curve, last_n: int) -> tuple[np.ndarray, np.ndarray]:
    """Each run's least-squares line through its success over its last min(last_n, E) epochs: (slope per epoch
    [R], residuals [N, R])."""
    chex.assert_rank(curve.success, 2)
    window = curve.success[-last_n:]
    x = curve.epoch[-last_n:] - curve.epoch[-last_n:].mean()
    slope = (x[:, None] * (window - window.mean(axis=0))).sum(axis=0) / max(float((x**2).sum()), 1e-12)
    return slope, window - window.mean(axis=0) - x[:, None] * slope


def residual_spread(curve: report.Curve, last_n: int) -> np.ndarray:
    """Each run's steadiness [R]: the std of its success around its own fitted linear trend over its last
    min(last_n, E) epochs (residual std, N − 2 degrees of freedom), so that a run still climbing through the window
    is not called unsteady for its climb (the paper's "mean standard deviation", Sec. IV-B, is their mean)."""
    _, residuals = window_fit(curve, last_n)
    return np.sqrt((residuals**2).sum(axis=0) / max(residuals.shape[0] - 2, 1))


def trend(curve: report.Curve, last_n: int) -> tuple[float, float, float]:
    """(mean, low, high): the Student-t 95 % interval over runs of their fitted slopes per epoch (`window_fit`)."""
    return stats.student_interval(window_fit(curve, last_n)[0])


MIN_MOVE = 0.01  # success over the window below which a fitted trend is no climb (one point of success)


def trending(curve: report.Curve, last_n: int) -> bool:
    """Whether the runs' success still moves over the window: their slopes' interval (`trend`) excludes 0 and the
    mean slope moves success by at least `MIN_MOVE` over the window's epochs."""
    mean, low, high = trend(curve, last_n)
    return bool((low > 0 or high < 0) and abs(mean) * (min(last_n, len(curve.epoch)) - 1) >= MIN_MOVE)


def trend_text(curve: report.Curve, last_n: int) -> str:
    """"+0.0100 [0.0080, 0.0120] an epoch": `trend`."""
    mean, low, high = trend(curve, last_n)
    return f"{mean:+.4f} [{low:.4f}, {high:.4f}] an epoch"


def eval_episodes(run: dict) -> int:
    """A run's eval episodes per seed and epoch: its config's eval_envs, else its env and agent preset's."""
    given = run["config"].get("train", {}).get("eval_envs")
    return int(given or cli.resolve({"env": run["env"], "agent": run["agent"]}).train.eval_envs)


def seeds_above_floor(run: dict, floors: report.Floors, last_n: int) -> np.ndarray | None:
    """Per seed [S], whether it is clearly above its task's floor over all goals (`report.seeds_above` of its eval
    success against the floor's upper bound, `report.Floor.bound`), a labelled variant's the floor of the task it
    derives from (`envs_mjx.lineage`); None where results/floors lacks the task."""
    task = next((name for name in envs_mjx.lineage(run["env"]) if "all" in floors.get(name, {})), None)
    if task is None:
        return None
    return report.seeds_above(run["success"], eval_episodes(run), floors[task]["all"].bound, last_n)


def above_floor(run: dict, floors: report.Floors, last_n: int) -> str:
    """"k/S above its floor" (`seeds_above_floor`); "" where results/floors lacks the task."""
    above = seeds_above_floor(run, floors, last_n)
    return "" if above is None else f"{int(above.sum())}/{above.size} above its floor"


def budget(run: dict, default: int | None = None) -> int:
    """A run's epoch budget: its config's epochs, or its experiment's `default` if more (by default its env and
    agent preset's)."""
    default = default or cli.resolve({"env": run["env"], "agent": run["agent"]}).run.epochs
    return max(int(run["config"]["run"].get("epochs", 0)), default)


def load_noise_curves(out: str) -> tuple[dict[tuple[float, str], report.Curve], dict[str, int]]:
    """The noise runs in `out`: (κ, agent) -> its runs' curve, and agent -> its epoch budget (the largest of its
    runs'). An agent's runs are one folder `<agent>` of 3 κ × R runs (`kappa_curves`), or a folder per κ
    (`kappa_dir`), or both for different κ; the same κ in both raises `report.RunError`."""
    found, budgets = {}, {}

    def add(run_dir: str, curves: Callable[[dict], list[tuple[float, report.Curve]]]) -> None:
        if not os.path.isfile(os.path.join(run_dir, "metrics.csv")):
            return
        run = report.load_run(run_dir)
        budgets[run["agent"]] = max(budgets.get(run["agent"], 0), budget(run, NOISE_EPOCHS))
        for k, curve in curves(run):
            if (k, run["agent"]) in found:
                raise report.RunError(f"{run_dir}: {run['agent']} at κ {k:.0%} is also in "
                                      f"{found[k, run['agent']].run_dir}; keep one of them")
            found[k, run["agent"]] = curve

    for agent in NOISE_AGENTS:
        add(os.path.join(out, agent), lambda run: list(zip(KAPPAS, kappa_curves(run, run["seeds"] // len(KAPPAS)))))
        for k in KAPPAS:
            add(os.path.join(out, kappa_dir(agent, k)), lambda run, k=k: [(k, kappa_curve(run, k))])
    return found, budgets


# ----- transfer (Fig. 6) -------------------------------------------------------------------------
SOURCE_ENV, TARGET_ENV, AGENT = "nicol_slide", "nicol_lift_reduced", "multimodal_bidal"
THRESHOLDS = (0.3, 0.5)


def seed_steps_to(curve: report.Curve, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Per seed [S]: env steps per seed at the first epoch whose success (that seed's) is ≥ `threshold`,
    censored at the run's last env steps for a seed that never reaches it; and which seeds were censored."""
    chex.assert_rank(curve.success, 2)
    reached = curve.success >= threshold
    steps = np.where(reached.any(axis=0), curve.env_steps[reached.argmax(axis=0)], curve.env_steps[-1])
    return steps, ~reached.any(axis=0)


def seed_measures(curve: report.Curve) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per-seed measures [S] of an arm, with which seeds are censored: AUC (mean success over the epochs)
    and env steps to each of THRESHOLDS (`seed_steps_to`)."""
    measures = {"AUC": (curve.success.mean(axis=0), np.zeros(curve.n_seeds, bool))}
    return {**measures, **{f"env steps to {t:g}": seed_steps_to(curve, t) for t in THRESHOLDS}}
