"""The paper's three claims, measured on our run folders, each with a verdict by a stated rule:

    python -m experiments.paper.claims --curves results/curves --noise results/noise --transfer results/transfer
        --out results/claims.md [--readme docs/reproduction.md] [--stale TASK[,TASK]] [--last-n 10]

(a) Learning (paper Sec. IV-A, Fig. 4): the BidAL agents learn every task and the visual baseline none; multimodal
    BidAL is best overall, most clearly on lifting. From `--curves` (OUT/<task>/<agent>,
    experiments/paper/curves.py), per seed: its final success (the mean of its last `--last-n` epochs), its
    normalised AUC (its mean success over all epochs: learning speed over the whole budget) and its env steps to
    0.5 and to 0.9 success (the first epoch its success reaches the threshold; a seed that never does counts the
    run's last env steps, its budget, and is named censored: its steps are understated, so a difference against
    its arm is understated, never overstated). On nicol_lift every figure is the success over air goals alone
    (metrics.csv's `eval_success_air`: a policy that slides but never lifts scores 0.5625 overall and 0.125
    there); a run without that column (older than it) is judged on its overall success and named in the rule.
    Checks: a run has learned a task when its final success (mean over seeds) is at least LEARNED; multimodal
    BidAL against the best other agent in each measure (final success, AUC, env steps to 0.5, to 0.9): each a
    bootstrap interval over seeds of the difference, over the mean over tasks for "best overall" (env steps as a
    share of each run's budget, so that tasks of other lengths weigh alike) and on nicol_lift for "most clearly on
    lifting" (env steps as they are), where also its final-success margin must be larger than on every other task;
    and the seeds that lift (final success over air goals ≥ LIFTS; without the column overall ≥ LIFTS_OVERALL,
    which implies it when half the goals lie in the air), k of n per agent with Wilson intervals, multimodal
    BidAL's against the other agent's with the largest share by Fisher's exact test (two-sided; favours or against
    when p < ALPHA, by the side, else unclear).
(b) Noise (Sec. IV-B, Table II): at κ = 10 and 15 % multimodal BidAL's success is steadier (each run's
    std over the last N epochs, the mean over runs) and higher (the mean over runs of each run's last-N
    mean) than both baselines'. From `--noise` (experiments/paper/noise_robustness.py).
(c) Transfer (Sec. IV-C, Fig. 6): reduced lift learns faster from nicol_slide's representation than
    from scratch: fewer env steps to 0.5 success, larger AUC (per seed, experiments/paper/transfer_learning.py). From
    `--transfer`.

Verdicts. Each claim is a list of checks, each of which favours the claim, is against it, or is unclear. A
comparison's check is its 95 % bootstrap interval over seeds (`stats.bootstrap_difference`): favours when the
interval lies on the claimed side of 0, against when on the other, else unclear; a threshold's check favours or is
against; Fisher's exact test as in (a). "reproduced": every check favours; "reversed": none favours and one is
against; "not reproduced": otherwise; "not measured": a run the claim needs is missing or short (fewer epochs than
its budget: the curves grid's epochs per task, or the env and agent preset's for the noise and transfer runs, or its
config's if more), its figures still shown; a learning claim needs the cells of the agents it is about (the λ = 0
row multimodal_bidal's and the ablation's, "best overall" and the lifting rows every paper agent's). Runs made on
other physics than the task's model today (config.json records the fingerprints of the physics a run trained on,
`envs_mjx.base.Env.physics_id`; runs older than that record none), and runs of a task named by `--stale`, get
their verdict qualified "measured on ... runs not recorded on today's physics".

Time: the file ends with what the runs on today's physics took, per experiment and per machine (config.json's
"hardware"; "not recorded" for runs older than that record): the sum of each run's last `wall_time_with_compile`.

The previous table: the section of `--out` from its line `## On the earlier tasks` to its end is kept when the
file is written again, so that the claims as judged on the earlier tasks' runs stay beside today's for
comparison; `--previous FILE` (a claims file this command wrote, e.g. `git show REV:results/claims.md`) starts
that section anew from FILE's table, its rules, notes and command, FILE's own earlier section left out.

`--readme FILE` also writes the table (without the rules), the time and the command into FILE, replacing the
text from its line `README_START` to its line `README_END`; a FILE without them is refused.

Exit codes: 0 written; 2 bad option, a run folder with a damaged file (the line names the file; the claims stop
rather than leave the run out), an --out folder that does not exist or cannot be written, or a --readme without
the block (one `error: ...` line; nothing written); 4 a write failed (no space, quota, read-only file system,
permission denied: one line); 130 stopped by Ctrl-C.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import os
import sys
from typing import Sequence

import numpy as np

from bidal_jax.config import AGENTS
from bidal_jax.run import rundir, runfiles
from experiments import cli, report, stats
from experiments.paper import grid, protocol

PROG = "python -m experiments.paper.claims"
LEARNED = 0.5  # final success at which a run has learned its task
BIDAL = ("visual_bidal", "multimodal_bidal")
OURS, VISUAL, LIFT = "multimodal_bidal", "visual_baseline", "nicol_lift"
ABLATION = "multimodal_bidal_no_ri"  # OURS without the intrinsic reward (λ = 0): no paper agent, never "the best other"
PAPER_AGENTS = tuple(a for a in AGENTS if a != ABLATION)
NOISE_KAPPAS = (0.10, 0.15)
BASELINES = ("multimodal_baseline", "proprio_baseline")
FAVOURS, AGAINST, UNCLEAR = "favours", "against", "unclear"
SPEED = (0.5, 0.9)  # success thresholds of claim (a)'s learning speed
FINAL, AUC = "final success", "AUC"
STEPS_TO = "env steps to {:g}"
MEASURES = (FINAL, AUC, *(STEPS_TO.format(t) for t in SPEED))
LIFTS = protocol.LIFTS  # a seed lifts when its final success over air goals is at least this
LIFTS_OVERALL = 0.75  # the same on overall success, for runs without air goals' success: air ≥ 2·overall − 1
ALPHA = 0.05  # Fisher's exact test: the p below which a difference of lifting seeds counts
NOT_MEASURED = "not measured"
README_START = "<!-- claims: written by experiments.paper.claims --readme; edits up to the end mark are lost -->"
README_END = "<!-- end of claims -->"
PREVIOUS = "## On the earlier tasks"


@dataclasses.dataclass(frozen=True)
class Claim:
    """One row of the claims table."""

    claim: str
    ours: str
    paper: str
    verdict: str
    rule: str


def compare(low: float, high: float, positive: bool) -> str:
    """A comparison's check from the 95 % interval of its difference; `positive`: the claim says it is > 0."""
    if low > 0 or high < 0:
        return FAVOURS if (low > 0) == positive else AGAINST
    return UNCLEAR


def verdict(checks: Sequence[str]) -> str:
    """"reproduced" (all favour), "reversed" (none favours, one is against) or "not reproduced"."""
    if not checks:
        raise ValueError("verdict: no checks")
    if all(c == FAVOURS for c in checks):
        return "reproduced"
    return "reversed" if AGAINST in checks and FAVOURS not in checks else "not reproduced"


def judged(checks: Sequence[str], gaps: Sequence[str], tasks: set[str], stale: set[str]) -> str:
    """The verdict of `checks`, "not measured: ..." when the runs have `gaps`, qualified by the stale tasks used."""
    text = f"{NOT_MEASURED}: {'; '.join(gaps[:3])}" + (f" (+{len(gaps) - 3} more)" if len(gaps) > 3 else "") \
        if gaps else verdict(checks)
    old = sorted(tasks & stale)
    return text + (f"; measured on {', '.join(old)} runs not recorded on today's physics" if old else "")


def gap(name: str, run: dict | None, budget: int) -> str | None:
    """Why a run cannot measure a claim: missing, or fewer epochs than `budget`; None if neither."""
    if run is None:
        return f"{name} missing"
    done = int(run["epoch"][-1])
    return f"{name} short ({done} of {budget} epochs)" if done < budget else None


def figure(values: np.ndarray) -> str:
    """A mean of success rates over seeds, its 95 % Student-t interval clipped to [0, 1] (`stats.rate_interval`)."""
    mean, low, high = stats.rate_interval(values)
    return f"{mean:.3f} {stats.interval_text(low, high)}"


def difference(a: Sequence[np.ndarray], b: Sequence[np.ndarray], digits: int = 3) -> tuple[str, float, float]:
    """(text "+d [low, high]", low, high) of `stats.bootstrap_difference(a, b)`."""
    diff, low, high = stats.bootstrap_difference(a, b)
    return f"{diff:+,.{digits}f} {stats.interval_text(low, high, digits)}", low, high


# ----- (a) learning curves ---------------------------------------------------------------------------


def load_grid(curves_dir: str) -> dict[tuple[str, str], dict | None]:
    """(task, agent) -> the run in CURVES/<task>/<agent> (`report.load_run`), None where it has no epochs."""
    return {(t, a): grid.loaded(os.path.join(curves_dir, t, a)) for t in protocol.paper_tasks() for a in AGENTS}


def judged_curve(run: dict) -> tuple[report.Curve, bool]:
    """(The curve claim (a) judges a run by, whether it is a nicol_lift run judged on its overall success for want
    of `report.AIR`): on nicol_lift each seed's success over air goals alone (a policy that slides but never lifts
    scores 0.5625 overall and 0.125 there, `never_lift_success`), elsewhere its eval success."""
    curve = report.curves([run])[0]
    if run["env"] != LIFT:
        return curve, False
    if run["success_air"] is None:
        return curve, True
    return dataclasses.replace(curve, success=run["success_air"]), False


def seed_figures(curve: report.Curve, last_n: int) -> Figures:
    """Per seed [S], with which seeds are censored: the final success (mean of its last `last_n` epochs), the
    normalised AUC (mean success over all epochs) and the env steps to each of `SPEED` (`protocol.seed_steps_to`:
    censored at the run's last env steps, its budget, where the seed never reaches it)."""
    none = np.zeros(curve.n_seeds, bool)
    figures = {FINAL: (report.final_per_seed(curve, last_n), none), AUC: (curve.success.mean(axis=0), none)}
    return {**figures, **{STEPS_TO.format(t): protocol.seed_steps_to(curve, t) for t in SPEED}}


Figures = dict[str, tuple[np.ndarray, np.ndarray]]  # `seed_figures`: measure -> (per seed [S], censored [S])


@dataclasses.dataclass(frozen=True)
class Grid:
    """The curves grid as claim (a) judges it."""

    figures: dict[tuple[str, str], Figures]  # (task, agent) -> `seed_figures` of its `judged_curve`
    budgets: dict[tuple[str, str], float]  # (task, agent) -> its run's last env steps per seed
    overall: tuple[str, ...]  # the agents whose nicol_lift run is judged on overall success (no `report.AIR`)


def grid_figures(runs: dict[tuple[str, str], dict | None], last_n: int) -> Grid:
    """The `Grid` of the runs that exist."""
    figures, budgets, overall = {}, {}, []
    for key, run in runs.items():
        if run:
            curve, fallback = judged_curve(run)
            figures[key], budgets[key] = seed_figures(curve, last_n), float(curve.env_steps[-1])
            overall += [key[1]] * fallback
    return Grid(figures, budgets, tuple(overall))


def grid_gaps(runs: dict[tuple[str, str], dict | None], agents: Sequence[str]) -> list[str]:
    """Why the cells of `agents` cannot measure a claim (`gap`): the runs of a claim about those agents alone, so
    that a missing cell of another agent (the λ = 0 ablation's) leaves it measured."""
    found = [gap(f"{t}/{a}", run, max(protocol.paper_epochs()[t], protocol.budget(run) if run else 0))
             for (t, a), run in runs.items() if a in agents]
    return [g for g in found if g]


def air_note(overall: Sequence[str]) -> str:
    """The rule's words on how nicol_lift is judged, naming the runs without `report.AIR` (judged on overall
    success instead)."""
    note = f"on {LIFT}, success over air goals ({report.AIR})"
    return note + (f"; its runs without that column ({', '.join(overall)}) on overall success" if overall else "")


def learning_claims(runs: dict[tuple[str, str], dict | None], last_n: int, stale: set[str]) -> list[Claim]:
    """Claim (a): six rows, from the curves grid, the last on where a gain of OURS comes from (`reward_claim`)."""
    measured = grid_figures(runs, last_n)
    final = {key: f[FINAL][0] for key, f in measured.figures.items()}
    tasks = set(protocol.paper_tasks())
    rule = f"learned: final success (mean over seeds of each seed's last {last_n} epochs; {air_note(measured.overall)}"
    rule += f") ≥ {LEARNED}"
    rows = []
    for name, agents, learns in ((f"(a) the BidAL agents ({', '.join(BIDAL)}) learn every task", BIDAL, True),
                                 (f"(a) the visual baseline ({VISUAL}) learns no task", (VISUAL,), False)):
        cells = {key: v for key, v in final.items() if key[1] in agents}
        checks = [FAVOURS if (v.mean() >= LEARNED) == learns else AGAINST for v in cells.values()]
        learned = sum(v.mean() >= LEARNED for v in cells.values())
        pick = (min if learns else max)(cells, key=lambda k: cells[k].mean(), default=None)
        ours = "—" if pick is None else (f"{'lowest' if learns else 'highest'}: {pick[1]} on {pick[0]} "
                                         f"{figure(cells[pick])}; {learned} of {len(cells)} runs learned")
        paper = "learn all tasks (Fig. 4)" if learns else "fails to learn any task (Fig. 4)"
        rows.append(Claim(name, ours, paper, judged(checks or [UNCLEAR], grid_gaps(runs, agents), tasks, stale), rule))
    rows += best_claims(measured, grid_gaps(runs, PAPER_AGENTS), stale, last_n)
    return [*rows, reward_claim(measured, grid_gaps(runs, (OURS, ABLATION)), stale)]


def reward_claim(measured: Grid, gaps: list[str], stale: set[str]) -> Claim:
    """Where a gain of OURS comes from: OURS against ABLATION, the same agent without the intrinsic reward (its
    forward and inverse losses kept), in every measure of `speed` over the tasks both ran. Favoured: the reward
    itself helps; unclear or against: any gain over the baselines is the representation losses'."""
    tasks = [t for t in protocol.paper_tasks() if (t, OURS) in measured.figures and (t, ABLATION) in measured.figures]
    name, paper = f"(a) {OURS} learns faster than {ABLATION} (λ = 0)", "not tested (the paper has no λ = 0 agent)"
    rule = speed_rule("every check favours").replace("the best other agent in that measure", ABLATION)
    if not tasks:
        return Claim(name, "—", paper, f"{NOT_MEASURED}: no {OURS} run beside an {ABLATION} run", rule)
    checks, texts = speed(measured.figures, measured.budgets, tasks, share=True, other=ABLATION)
    rule += f"; each the mean over tasks, steps as a share of each run's budget; {air_note(measured.overall)}"
    return Claim(name, "mean over tasks: " + "; ".join(texts), paper, judged(checks, gaps, set(tasks), stale), rule)


def best_other(values: dict[tuple[str, str], np.ndarray], tasks: Sequence[str], higher: bool) -> str:
    """The paper's agent other than OURS, with a run on every one of `tasks`, whose seeds' `values` are best on
    average over them (largest, or smallest where `higher` is False)."""
    others = [a for a in PAPER_AGENTS if a != OURS and all((t, a) in values for t in tasks)]
    return (max if higher else min)(others, key=lambda a: np.mean([values[t, a].mean() for t in tasks]))


def margin(values: dict[tuple[str, str], np.ndarray], tasks: Sequence[str], higher: bool, digits: int = 3,
           other: str | None = None) -> tuple[str, str, float, float]:
    """(`other`, by default the best other agent by the mean over `tasks` of its seeds' `values`, text, low, high)
    of OURS − that agent (`difference`: seeds resampled within each task); `higher`: whether larger values are
    better."""
    best = other or best_other(values, tasks, higher)
    text, low, high = difference([values[t, OURS] for t in tasks], [values[t, best] for t in tasks], digits)
    return best, text, low, high


def speed(figures: dict[tuple[str, str], Figures], budgets: dict[tuple[str, str], float], tasks: Sequence[str],
          share: bool, other: str | None = None) -> tuple[list[str], list[str]]:
    """(checks, texts) of OURS against `other`, by default the best other agent in each of `MEASURES`, over `tasks`:
    final success and
    AUC larger, env steps to each of `SPEED` fewer (`share`: as a share of each run's budget, so that tasks of
    other lengths weigh alike), each by its bootstrap 95 % interval; a text names the censored seeds."""
    checks, texts = [], []
    for name in MEASURES:
        higher = name in (FINAL, AUC)
        values = {key: f[name][0] / (budgets[key] if share and not higher else 1.0) for key, f in figures.items()}
        digits = 3 if higher or share else 0
        best, text, low, high = margin(values, tasks, higher, digits, other)
        censored = sum(int(figures[t, a][name][1].sum()) for t in tasks for a in (OURS, best))
        seeds = sum(figures[t, a][name][1].size for t in tasks for a in (OURS, best))
        label = f"{name} (share of the budget)" if share and not higher else name
        checks.append(compare(low, high, higher))
        texts.append(f"{label} {text} over {best}" + (f" ({censored} of {seeds} seeds censored)" if censored else ""))
    return checks, texts


def speed_rule(what: str) -> str:
    """The words of the checks of `speed`."""
    return (f"{what}: for each of final success, AUC (each seed's mean success over all epochs) and env steps per "
            f"seed to {' and to '.join(f'{t:g}' for t in SPEED)} (a seed that never gets there counts the run's "
            "budget, its last env steps: censored), the bootstrap 95 % interval of OURS − the best other agent in "
            "that measure over seeds lies on OURS's side of 0 (larger success and AUC, fewer steps)").replace(
                "OURS", OURS)


def best_claims(measured: Grid, gaps: list[str], stale: set[str], last_n: int) -> list[Claim]:
    """Claim (a), second part: multimodal BidAL best overall (over the tasks' mean), most clearly on lifting,
    on more seeds that lift."""
    figures = measured.figures
    tasks = [t for t in protocol.paper_tasks() if (t, OURS) in figures]
    names = ((f"(a) {OURS} is best overall", "best overall (Fig. 4)"),
             (f"(a) {OURS} leads most clearly on {LIFT}", "especially on lifting (Fig. 4)"),
             (f"(a) more of {OURS}'s seeds lift than of any other agent", "especially on lifting (Fig. 4)"))
    if not tasks or not any(all((t, a) in figures for t in tasks) for a in PAPER_AGENTS if a != OURS):
        why = f"{NOT_MEASURED}: no {OURS} run beside another agent's on the same tasks"
        return [Claim(c, "—", p, why, "") for c, p in names]
    checks, texts = speed(figures, measured.budgets, tasks, share=True)
    overall = Claim(
        names[0][0], "mean over tasks: " + "; ".join(texts), names[0][1],
        judged(checks, gaps, set(tasks), stale),
        speed_rule("every check favours") + "; each the mean over tasks, steps as a share of each run's budget, "
        f"seeds resampled within each run; {air_note(measured.overall)}")
    if LIFT not in tasks:
        why = f"{NOT_MEASURED}: {LIFT} missing"
        return [overall, *(Claim(c, "—", p, why, "") for c, p in names[1:])]
    final = {key: f[FINAL][0] for key, f in figures.items()}
    margins = {t: final[t, OURS].mean() - final[t, best_other(final, [t], True)].mean() for t in tasks}
    checks, texts = speed(figures, measured.budgets, [LIFT], share=False)
    checks += [FAVOURS if margins[LIFT] > margins[t] else AGAINST for t in tasks if t != LIFT]
    rest = ", ".join(f"{t} {margins[t]:+.3f}" for t in tasks if t != LIFT)
    lift = Claim(
        names[1][0], f"{LIFT}: " + "; ".join(texts) + f"; final-success margin on other tasks: {rest}", names[1][1],
        judged(checks, gaps, set(tasks), stale),
        speed_rule(f"on {LIFT}") + f", and its final-success margin over the best other agent is larger on {LIFT} "
        f"than on every other task; {air_note(measured.overall)}")
    return [overall, lift, lifting_claim(final, measured.overall, gaps, stale, last_n, names[2])]


def lifts(final_air: np.ndarray, overall: bool) -> int:
    """How many seeds lift: final success over air goals ≥ `LIFTS`, or, judged on overall success (a run without
    `report.AIR`), overall ≥ `LIFTS_OVERALL`, which implies the former when half the goals lie in the air."""
    return int((final_air >= LIFTS_OVERALL).sum()) if overall else protocol.seeds_that_lift(final_air)


def lifting_claim(final: dict[tuple[str, str], np.ndarray], overall: Sequence[str], gaps: list[str], stale: set[str],
                  last_n: int, name: tuple[str, str]) -> Claim:
    """Claim (a) on lifting, by seeds: OURS's seeds that lift (`lifts`) against the other agent with the largest
    share of lifting seeds on nicol_lift, by Fisher's exact test; each share with its Wilson 95 % interval."""
    agents = [a for a in AGENTS if (LIFT, a) in final]
    counted_seeds = {a: (lifts(final[LIFT, a], a in overall), final[LIFT, a].size) for a in agents}
    share = {a: f"{a} {k}/{n} {stats.interval_text(*stats.wilson_interval(k, n))}"
             for a, (k, n) in counted_seeds.items()}
    others = [a for a in agents if a not in (OURS, ABLATION)]
    rule = (f"a seed lifts when its success over air goals over its last {last_n} epochs is ≥ {LIFTS} (runs "
            f"without {report.AIR}: overall success ≥ {LIFTS_OVERALL}); Fisher's exact test (two-sided) of {OURS}'s "
            f"lifting seeds against those of the other agent with the largest share: favours when p < {ALPHA} and "
            f"{OURS}'s share is larger, against when p < {ALPHA} and smaller; intervals: Wilson 95 % of each share")
    if OURS not in counted_seeds or not others:
        return Claim(name[0], "—", name[1], f"{NOT_MEASURED}: no {OURS} run beside another agent's on {LIFT}", rule)
    best = max(others, key=lambda a: counted_seeds[a][0] / counted_seeds[a][1])
    (k, n), (k_b, n_b) = counted_seeds[OURS], counted_seeds[best]
    p = stats.fisher_p(k, n, k_b, n_b)
    check = UNCLEAR if p >= ALPHA else FAVOURS if k / n > k_b / n_b else AGAINST
    ours = f"lifting seeds: {'; '.join(share.values())}; Fisher {OURS} vs {best}: p = {p:.3g}"
    return Claim(name[0], ours, name[1], judged([check], gaps, {LIFT}, stale), rule)


# ----- (b) noise -------------------------------------------------------------------------------------


def noise_claims(noise_dir: str, stale: set[str]) -> list[Claim]:
    """Claim (b): steadier and higher than both baselines at κ = 10 and 15 %."""
    found, budgets = protocol.load_noise_curves(noise_dir) if os.path.isdir(noise_dir) else ({}, {})
    agents = (OURS, *BASELINES)
    gaps = [f"{a} missing" for a in agents if a not in budgets]
    gaps += [f"{a} at κ {k:.0%} missing" for a in agents if a in budgets for k in NOISE_KAPPAS if (k, a) not in found]
    measured = {found[k, a].run_dir: found[k, a] for a in agents for k in NOISE_KAPPAS if (k, a) in found}
    gaps += [f"{os.path.basename(run_dir)} short ({int(curve.epoch[-1])} of {budgets[curve.label]} epochs)"
             for run_dir, curve in measured.items() if curve.epoch[-1] < budgets[curve.label]]
    tasks = {report.load_run(run_dir)["env"] for run_dir in measured}
    measures = (
        ("steadier", "each run's std of its success over the last N epochs", protocol.steadiness, False, 1),
        ("higher", "each run's mean success over the last N epochs", report.final_per_seed, True, 0),
    )
    rows = []
    for word, what, measure, positive, column in measures:
        checks, ours, paper = [], [], []
        for k in NOISE_KAPPAS:
            paper.append(f"{k:.0%}: " + " vs ".join(f"{protocol.PAPER[k][a][column]:.3f}" for a in agents))
            if (k, OURS) not in found:
                continue
            mine = measure(found[k, OURS], protocol.LAST_N[k])
            cells = [f"{mine.mean():.4f}"]
            for b in (b for b in BASELINES if (k, b) in found):
                text, low, high = difference([mine], [measure(found[k, b], protocol.LAST_N[k])], 4)
                checks.append(compare(low, high, positive))
                cells.append(f"− {b} {text}")
            ours.append(f"{k:.0%}: " + "; ".join(cells))
        rows.append(Claim(
            f"(b) under 10 and 15 % noise {OURS}'s success is {word} than both baselines'",
            " / ".join(ours) or "—", " / ".join(paper) + f" ({', '.join(agents)}; Table II "
            + ("±, \"mean standard deviation\")" if column else "means)"),
            judged(checks or [UNCLEAR], gaps, tasks, stale),
            f"per κ and baseline: bootstrap 95 % interval of {OURS} − baseline over runs of {what} (N = "
            f"{', '.join(str(protocol.LAST_N[k]) for k in NOISE_KAPPAS)}) {'above' if positive else 'below'} 0"))
    return rows


# ----- (c) transfer ----------------------------------------------------------------------------------


def transfer_claims(transfer_dir: str, stale: set[str]) -> list[Claim]:
    """Claim (c): fewer env steps to 0.5 and a larger AUC from nicol_slide's representation than from scratch."""
    runs = {name: grid.loaded(os.path.join(transfer_dir, name)) for name in ("transfer", "scratch", "source")}
    gaps = [g for name in ("transfer", "scratch") if (g := gap(name, runs[name], protocol.budget(runs[name])
                                                             if runs[name] else 0))]
    tasks = {run["env"] for run in runs.values() if run} | ({protocol.SOURCE_ENV} if runs["transfer"] else set())
    paper = "learns faster with the slide representation (Fig. 6; no figure given)"
    if runs["transfer"] is None or runs["scratch"] is None:
        return [Claim(f"(c) reduced lift learns faster from {protocol.SOURCE_ENV} ({what})", "—", paper,
                      judged([], gaps, tasks, stale), "") for what in ("env steps to 0.5", "AUC")]
    arms = {name: protocol.seed_measures(report.curves([runs[name]])[0]) for name in ("transfer", "scratch")}
    rows = []
    for key, positive, digits in (("env steps to 0.5", False, 0), ("AUC", True, 3)):
        (a, a_cut), (b, b_cut) = arms["transfer"][key], arms["scratch"][key]
        text, low, high = difference([a], [b], digits)
        censored = a_cut.sum() + b_cut.sum()
        note = f" ({censored} of {a.size + b.size} seeds censored at their run's env steps)" if censored else ""
        rows.append(Claim(
            f"(c) reduced lift learns faster from {protocol.SOURCE_ENV} ({key}, transfer − scratch)",
            f"{a.mean():,.{digits}f} − {b.mean():,.{digits}f} = {text}{note}", paper,
            judged([compare(low, high, positive)], gaps, tasks, stale),
            f"bootstrap 95 % interval of transfer − scratch over seeds {'below' if not positive else 'above'} 0"))
    return rows


# ----- the report ------------------------------------------------------------------------------------


def claims_table(rows: Sequence[Claim]) -> str:
    return report.markdown_table(["claim", "ours (95 % interval)", "paper", "verdict", "rule"],
                                 [[r.claim, r.ours, r.paper, r.verdict, r.rule] for r in rows])


def runs_below(folder: str) -> list[dict]:
    """Every run folder with epochs below `folder` (`report.load_run`), in walking order; a damaged one raises
    `report.RunError` naming its file (the claims stop on it: exit 2)."""
    runs = []
    for where, _, files in sorted(os.walk(folder)):
        if "config.json" not in files:
            continue
        try:
            runs.append(report.load_run(where))
        except report.NotARun:
            continue  # no epochs yet: not a run the claims read (they say why where they need it)
    return runs


def on_other_physics(runs: Sequence[dict]) -> list[dict]:
    """The runs that trained on other physics than their env steps today (`grid.other_physics`: a run whose
    config.json records fingerprints, `Env.physics_id`, other than today's alone, or none: runs older than the
    record). Runs of tasks no longer registered are left out."""
    today = grid.physics_today(run["env"] for run in runs)
    return [run for run in runs if grid.other_physics(run["config"], today[run["env"]])]


def per_task(runs: Sequence[dict]) -> dict[str, int]:
    """Task -> how many of `runs` are of it."""
    return dict(collections.Counter(run["env"] for run in runs))


def counted(tasks: dict[str, int]) -> str:
    """"nicol_slide (1 run), nicol_lift (2 runs)" for task -> count."""
    return ", ".join(f"{task} ({count(n, 'run')})" for task, n in sorted(tasks.items()))


def hours(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h"


def count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def time_report(experiments: dict[str, list[dict]], old: set[str]) -> str:
    """What the runs behind the claims took: per experiment (name -> its runs, `runs_below`) and per machine, the
    sum of each run's last `wall_time_with_compile` (training and compiling, summed over its processes; `wall_time`,
    compiling not counted, where metrics.csv predates that column: `report.last_time`), for the runs on today's
    physics; the runs whose folders are in `old` (on other physics: `on_other_physics`) apart, or a line that
    there are none."""
    per_experiment, per_machine, other, others, without_compile = [], {}, 0.0, 0, 0
    for name, runs in experiments.items():
        stale = {run["dir"] for run in runs} & old
        others += len(stale)
        total = 0.0
        for run in runs:
            seconds, with_compile = report.last_time(run)
            if run["dir"] in stale:
                other += seconds
                continue
            total += seconds
            without_compile += not with_compile
            machines = run["config"].get("hardware") or ["not recorded"]
            key = " then ".join(machines)
            per_machine[key] = per_machine.get(key, 0.0) + seconds
        per_experiment.append(f"{name} {hours(total)} ({count(len(runs) - len(stale), 'run')})")
    machines = "; ".join(f"{machine}: {hours(seconds)}" for machine, seconds in sorted(per_machine.items()))
    return (f"Time of the runs behind these claims, on today's physics: {', '.join(per_experiment)}; in all "
            f"{hours(sum(per_machine.values()))} (per machine, as config.json records it: {machines or 'none'}). "
            "Each run counts its last `wall_time_with_compile`: training and compiling, summed over its processes"
            + (f"; runs older than that column ({without_compile}) count their `wall_time`, compiling not counted"
               if without_compile else "")
            + (f". Runs on other physics, not counted: {hours(other)} ({count(others, 'run')})." if others
               else ". No run is on other physics."))


def claims_report(curves_dir: str, noise_dir: str, transfer_dir: str, stale: set[str], last_n: int,
                  command: str) -> tuple[str, str]:
    """(results/claims.md's text, the README's block: `readme_block`)."""
    runs = {folder: runs_below(folder) for folder in (curves_dir, noise_dir, transfer_dir)}
    old = {run["dir"] for run in on_other_physics([run for found in runs.values() for run in found])}
    other = {folder: per_task([run for run in found if run["dir"] in old]) for folder, found in runs.items()}
    rows = [*learning_claims(load_grid(curves_dir), last_n, stale | set(other[curves_dir])),
            *noise_claims(noise_dir, stale | set(other[noise_dir])),
            *transfer_claims(transfer_dir, stale | set(other[transfer_dir]))]
    found = "; ".join(f"{folder}: {counted(tasks)}" for folder, tasks in other.items() if tasks)
    times = time_report({"learning curves": runs[curves_dir], "noise": runs[noise_dir],
                         "transfer": runs[transfer_dir]}, old)
    text = "\n".join([
        "# The paper's three claims, measured",
        "",
        f"From the run folders {curves_dir}, {noise_dir} and {transfer_dir}. Intervals: 95 %, a Student-t "
        "interval over seeds for a figure (clipped to [0, 1], the range of a success rate), a bootstrap over seeds "
        "(10,000 resamples, fixed seed) for a difference. Verdict rule (experiments/paper/claims.py): every check "
        "favours the claim: reproduced; none favours and one is against: reversed; otherwise not reproduced; a run "
        "missing or short: not measured.",
        "",
        claims_table(rows),
        "",
        *([f"Runs not recorded on today's physics (their config.json records another fingerprint of the model, "
           f"`Env.physics_id`, or, older than that record, none; they qualify the verdicts of their folder's "
           f"claims): {found}.", ""] if found else []),
        *([f"Named stale (--stale): {', '.join(sorted(stale))}.", ""] if stale else []),
        times,
        "",
        f"Regenerate: `{command}`",
        "",
    ])
    return text, readme_block(rows, times, command)


def previous_section(path: str, start: bool) -> str:
    """The section `PREVIOUS` to keep: with `start`, a new one from the claims file `path` (`--previous`: its text
    less its title and its own `PREVIOUS` section); else the one already in `path` (`--out`), "" when it has
    none or does not exist. ValueError when `path` cannot be read (or, with `start`, is not a claims file)."""
    try:
        with open(path) as f:
            text = f.read()
    except FileNotFoundError:
        if start:
            raise ValueError(f"--previous {path}: no such file") from None
        return ""
    except OSError as err:
        raise ValueError(f"{'--previous' if start else '--out'} {path}: cannot read it ({err.strerror})") from err
    at = text.find(f"\n{PREVIOUS}\n")
    if not start:
        return "" if at < 0 else text[at + 1:].rstrip("\n") + "\n"
    title, _, body = text[:at if at >= 0 else len(text)].partition("\n")
    if not title.startswith("# "):
        raise ValueError(f"--previous {path}: not a claims file (its first line is no '# ' title)")
    return "\n".join([PREVIOUS, "", f"\"{title[2:]}\" as this command wrote it from the runs of the earlier tasks, "
                      "kept verbatim for comparison: its figures, rules and notes are those of the code that wrote "
                      "it (in git's history); its command now writes the table above.", "", body.strip("\n"), ""])


def readme_block(rows: Sequence[Claim], times: str, command: str) -> str:
    """The claims block of a document (docs/reproduction.md): the table without its rules, the time line and
    the command, between `README_START` and `README_END`."""
    table = report.markdown_table(["claim", "ours (95 % interval)", "paper", "verdict"],
                                  [[r.claim, r.ours, r.paper, r.verdict] for r in rows])
    return "\n".join([README_START, table, "", times, "", f"Regenerate: `{command}` (the rules of the verdicts "
                      "are in the file it writes)", README_END])


def write_readme(path: str, block: str) -> None:
    """Replace the text from `README_START` to `README_END` in the file `path` by `block`; ValueError (nothing
    written) when the file lacks them."""
    try:
        with open(path) as f:
            text = f.read()
    except OSError as err:
        raise ValueError(f"--readme {path}: cannot read it ({err.strerror})") from err
    start, end = text.find(README_START), text.find(README_END)
    if start < 0 or end < start:
        raise ValueError(f"--readme {path}: no claims block to replace; it needs the line {README_START!r} and, "
                         f"after it, the line {README_END!r}")
    with rundir.writing(path):
        runfiles.write_atomic(path, text[:start] + block + text[end + len(README_END):])


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("--curves", default=os.path.join("results", "curves"), help="the curves grid's folder")
    parser.add_argument("--noise", default=os.path.join("results", "noise"), help="the noise experiment's folder")
    parser.add_argument("--transfer", default=os.path.join("results", "transfer"), help="the transfer folder")
    parser.add_argument("--out", default=os.path.join("results", "claims.md"), help="the Markdown file written")
    parser.add_argument("--stale", default="", help="comma list of tasks whose runs to count as made on other "
                        "physics than today's besides those whose config.json says so (their verdicts say so)")
    parser.add_argument("--last-n", type=int, default=10, help="epochs of the curves' final success")
    parser.add_argument("--previous", default=None, metavar="FILE", help=f"a claims file this command wrote: its "
                        f"table becomes the section '{PREVIOUS}' of --out (without it, --out's own such section "
                        "is kept)")
    parser.add_argument("--readme", default=None, help="also write the claims (without their rules) into this "
                        "file, between its lines README_START and README_END (e.g. docs/reproduction.md)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        stale = set(cli.parse_names(args.stale, "--stale", "task", (*protocol.paper_tasks(), protocol.TARGET_ENV))) \
            if args.stale else set()
        if args.last_n < 1:
            raise ValueError(f"--last-n {args.last_n}: must be a positive integer")
        runfiles.check_output_dir(os.path.dirname(args.out), "--out")  # before the work, not after it
    except ValueError as err:
        return cli.exit_code(err)
    options = [f"--curves {args.curves}", f"--noise {args.noise}", f"--transfer {args.transfer}", f"--out {args.out}"]
    options += [f"--stale {args.stale}"] * bool(args.stale) + [f"--last-n {args.last_n}"] * (args.last_n != 10)
    options += [f"--readme {args.readme}"] * bool(args.readme)
    try:
        previous = previous_section(args.previous or args.out, start=bool(args.previous))
        text, block = claims_report(args.curves, args.noise, args.transfer, stale, args.last_n,
                                    " ".join([PROG, *options]))
        text += f"\n{previous}" if previous else ""
        if args.readme:
            write_readme(args.readme, block)
        with rundir.writing(args.out):
            runfiles.write_atomic(args.out, text)
    except (ValueError, rundir.DiskError) as err:  # e.g. a run folder damaged, a noise κ in two folders, no block
        return cli.exit_code(err)
    print(f"{text}\nwritten to {args.out}" + (f" and {args.readme}" if args.readme else ""))
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
