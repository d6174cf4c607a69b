"""The paper's three claims, measured on our run folders, each with a verdict by a rule fixed before the runs are read:

    python -m experiments.paper.claims --curves results/curves --noise results/noise --transfer results/transfer
        [--plain results/curves-plain] [--floors results/floors] --out results/claims.md [--readme docs/reproduction.md]
        [--stale TASK[,TASK]] [--last-n 10]

Every comparison is named in advance (no comparator is picked from the data), has one primary measure that decides
(`PRIMARY`, AUC: each seed's mean success over all epochs, learning speed over the whole budget) while the others are
reported, and where several checks decide one claim their p-values are Holm-corrected (`stats.holm`). A difference
is Welch's t over seeds (`stats.welch_difference`: a percentile bootstrap undercovers at 5 seeds). A success measure
where both arms are within `CEILING` of 1 is "at the ceiling" and does not decide. Floors: each task's success of a
policy that does nothing (`report.load_floors`, written by `python -m experiments.probes.floors`).

(a) Learning (paper Sec. IV-A, Fig. 4), from `--curves` (OUT/<task>/<agent>, experiments/paper/curves.py); on
    nicol_lift every figure is the success over air goals alone (metrics.csv's `eval_success_air`; a run without
    that column is judged on its overall success and named in the rule, and then so are the arms it is compared
    with: a comparison reads one measure). Every run is judged over its task's budget (`cell_budget`: a longer run
    is cut to it), so that the arms compared share their epochs.
    - The BidAL agents learn every task, the visual baseline none: a run has learned when every seed is clearly above
      its task's floor (`report.seeds_above`: a one-sided binomial test of its last `--last-n` epochs' eval episodes
      against the floor, Holm over the seeds; on nicol_lift's air goals the floor is at least `LIFT_NEVER`, what a
      policy that slides but never lifts scores), and has failed when no seed is.
    - Best overall: `OURS` against the paper's baselines (`PAPER_BASELINES`), AUC over the mean over tasks, Holm
      over the two; final success and env steps to 0.5 and 0.9 (a share of each run's budget; a seed that never gets
      there counts the budget: censored) reported.
    - Most clearly on lifting: its AUC margin on nicol_lift less its mean margin on the other tasks (a contrast),
      against proprio_baseline (`LIFT_BASELINES`: against the visual baseline, which learns next to nothing
      anywhere, the margin would be OURS's own level).
    - Added arms (`ADDED`, not in the paper), each its own row: OURS against multimodal_baseline and against the
      λ = 0 ablation (where a gain comes from), AUC over the mean over tasks.
    - Lifting seeds (a seed lifts when its final success over air goals is ≥ LIFTS), Fisher's exact test of OURS's
      against each paper baseline's, Holm over the two: under held starts from `--curves`, and under the plain
      protocol (`--exploration-starts 0`) from `--plain` (PLAIN/nicol_lift/<agent>, as the curves grid writes it),
      OURS and the multimodal baseline (an added arm) against proprio_baseline; "not measured" until those runs exist.
(b) Noise (Sec. IV-B, Table II), from `--noise` (experiments/paper/noise_robustness.py): at κ = 10 and 15 %, OURS's
    success is steadier (each run's residual std around its own fitted trend over the last N epochs,
    `protocol.residual_spread`) and higher (each run's last-N mean) than both baselines', Welch over runs, Holm over
    the four checks of each row. Steadiness is "not measured" while a curve still moves over the window
    (`protocol.trending`: its runs' slope interval excludes 0 and the mean slope moves success by at least
    `protocol.MIN_MOVE` over the window): a spread around a climb is the climb's.
(c) Transfer (Sec. IV-C, Fig. 6): reduced lift learns faster from nicol_slide's representation than from scratch:
    transfer − scratch in AUC (primary), env steps to 0.3 and 0.5 reported. From `--transfer`.

Verdicts. A check favours the claim, is against it, is unclear, or is at the ceiling (which does not decide).
"reproduced": every deciding check favours; "reversed": none favours and one is against (so a comparison is reversed
only where its primary measure's interval lies against the claim); "not reproduced": otherwise; "not measured": a
run the claim needs is missing or short (fewer epochs than its budget: the curves grid's epochs per task, or for the
noise and transfer runs the smallest of the compared arms' budgets, each the env and agent preset's or its config's
if more, to which the longer arms are cut; or fewer seeds with epochs than its cell's seed blocks plan), a task
lacks its floor, or a steadiness would be read on a climb; its figures still shown. Runs made on other physics than
the task's model today (config.json's fingerprints, `envs_mjx.base.Env.physics_id`; runs older than that record
none), and runs of a task named by `--stale`, get their verdict qualified "measured on ... runs not recorded on
today's physics".

Time: the file ends with the machine time the runs on today's physics held (`report.machine_shares`: wall time ×
the GPUs of their machine, runs that shared a GPU counted once as the experiments' figures.json record it, a group's
time shared by its runs), per experiment and in all, and beside it the summed process time per machine
(config.json's "hardware").

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
import types
from typing import Sequence

import numpy as np

from bidal_jax.config import AGENTS
from bidal_jax.run import rundir, runfiles
from envs_mjx.nicol import AIR_GOAL_PROBABILITY, NicolLift
from experiments import cli, report, stats
from experiments.paper import grid, protocol

PROG = "python -m experiments.paper.claims"
BIDAL = ("visual_bidal", "multimodal_bidal")
OURS, VISUAL, PROPRIO, LIFT = "multimodal_bidal", "visual_baseline", "proprio_baseline", "nicol_lift"
ABLATION = "multimodal_bidal_no_ri"  # OURS without the intrinsic reward (λ = 0): an added arm, no paper agent
PAPER_BASELINES = (PROPRIO, VISUAL)  # Fig. 4's comparisons: the paper's baselines
# "especially on lifting" is a margin larger on lifting than elsewhere: against the baseline that learns the tasks
# (against visual_baseline, which learns next to nothing anywhere, the margin would be OURS's own level)
LIFT_BASELINES = (PROPRIO,)
ADDED = ("multimodal_baseline", ABLATION)  # our added arms, each compared on its own row
NOISE_KAPPAS = (0.10, 0.15)
BASELINES = ("multimodal_baseline", "proprio_baseline")  # Table II's
FAVOURS, AGAINST, UNCLEAR, AT_CEILING = "favours", "against", "unclear", "at the ceiling"
SPEED = (0.5, 0.9)  # success thresholds of claim (a)'s learning speed
FINAL, AUC = "final success", "AUC"
PRIMARY = AUC  # the measure that decides a comparison of learning speed
STEPS_TO = "env steps to {:g}"
MEASURES = (AUC, FINAL, *(STEPS_TO.format(t) for t in SPEED))
CEILING = 0.02  # a success measure where both arms are within this of 1 does not decide
LIFTS = protocol.LIFTS  # a seed lifts when its final success over air goals is at least this
LIFTS_OVERALL = 0.75  # the same on overall success, for runs without air goals' success: air ≥ 2·overall − 1
# what a policy that slides perfectly but never lifts scores over nicol_lift's air goals (its method reads only the
# share of air goals, which this value does not depend on)
LIFT_NEVER = NicolLift.never_lift_success(types.SimpleNamespace(air_goal_probability=AIR_GOAL_PROBABILITY))["air"]
ALPHA = 0.05  # the level of every test: a check decides when its (Holm-adjusted) p is below it
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


def check(diff: stats.Difference, p: float, positive: bool, ceiling: bool = False) -> str:
    """A comparison's check from its difference and its (Holm-adjusted) p: favours when p < ALPHA and the difference
    lies on the claimed side (`positive`: the claim says it is > 0), against when p < ALPHA on the other, else
    unclear; `AT_CEILING` (it does not decide) where `ceiling`."""
    if ceiling:
        return AT_CEILING
    if np.isnan(p) or p >= ALPHA:
        return UNCLEAR
    return FAVOURS if (diff.point > 0) == positive else AGAINST


def verdict(checks: Sequence[str]) -> str:
    """Of the deciding checks (all but `AT_CEILING`): "reproduced" (all favour), "reversed" (none favours, one is
    against) or "not reproduced"; "not reproduced (at the ceiling)" when none decides."""
    if not checks:
        raise ValueError("verdict: no checks")
    deciding = [c for c in checks if c != AT_CEILING]
    if not deciding:
        return "not reproduced (at the ceiling: no check decides)"
    if all(c == FAVOURS for c in deciding):
        return "reproduced"
    return "reversed" if AGAINST in deciding and FAVOURS not in deciding else "not reproduced"


def judged(checks: Sequence[str], gaps: Sequence[str], tasks: set[str], stale: set[str]) -> str:
    """The verdict of `checks`, "not measured: ..." when the runs have `gaps`, qualified by the stale tasks used."""
    text = f"{NOT_MEASURED}: {'; '.join(gaps[:3])}" + (f" (+{len(gaps) - 3} more)" if len(gaps) > 3 else "") \
        if gaps else verdict(checks)
    old = sorted(tasks & stale)
    return text + (f"; measured on {', '.join(old)} runs not recorded on today's physics" if old else "")


def gap(name: str, run: dict | None, budget: int) -> str | None:
    """Why a run cannot measure a claim: missing, fewer epochs than `budget`, or fewer seeds with epochs than its
    cell's blocks plan ("planned_seeds", `report.load_run`); None if none of these."""
    if run is None:
        return f"{name} missing"
    done, planned = int(run["epoch"][-1]), run.get("planned_seeds", run["seeds"])
    if run["seeds"] < planned:
        return f"{name} short ({run['seeds']} of {planned} seeds)"
    return f"{name} short ({done} of {budget} epochs)" if done < budget else None


def figure(values: np.ndarray) -> str:
    """A mean of success rates over seeds, its 95 % Student-t interval clipped to [0, 1] (`stats.rate_interval`)."""
    mean, low, high = stats.rate_interval(values)
    return f"{mean:.3f} {stats.interval_text(low, high)}"


def difference_text(diff: stats.Difference, digits: int = 3) -> str:
    """"+d [low, high]" of a `stats.Difference`."""
    return f"{diff.point:+,.{digits}f} {stats.interval_text(diff.low, diff.high, digits)}"


def holm_deciding(diffs: Sequence[stats.Difference], ceilings: Sequence[bool]) -> dict[int, float]:
    """Index -> Holm-adjusted p (`stats.holm`) of the comparisons `diffs` of one claim that are not at the ceiling;
    those at the ceiling do not decide and have none."""
    deciding = [i for i, c in enumerate(ceilings) if not c]
    return dict(zip(deciding, stats.holm([diffs[i].p for i in deciding]))) if deciding else {}


def holm_checks(diffs: Sequence[stats.Difference], positive: bool, ceilings: Sequence[bool]) -> list[str]:
    """The checks of the deciding comparisons `diffs` of one claim: their p Holm-adjusted over those that are not
    at the ceiling (`holm_deciding`), each by `check`."""
    adjusted = holm_deciding(diffs, ceilings)
    return [check(d, adjusted.get(i, np.nan), positive, ceilings[i]) for i, d in enumerate(diffs)]


# ----- (a) learning curves ---------------------------------------------------------------------------


def load_grid(curves_dir: str, tasks: Sequence[str] = protocol.paper_tasks()) -> dict[tuple[str, str], dict | None]:
    """(task, agent) -> the run in CURVES/<task>/<agent> (`report.load_run`), None where it has no epochs."""
    return {(t, a): grid.loaded(os.path.join(curves_dir, t, a)) for t in tasks for a in AGENTS}


def judged_curve(run: dict, overall: bool = False) -> tuple[report.Curve, bool]:
    """(The curve claim (a) judges a run by, whether it is a nicol_lift run judged on its overall success): on
    nicol_lift each seed's success over air goals alone (a policy that slides but never lifts scores 0.5625 overall
    and 0.125 there, `never_lift_success`), unless the run lacks `report.AIR` or `overall` asks for overall success
    (an arm it is compared with lacks it: both arms on one measure); elsewhere its eval success."""
    curve = report.curves([run])[0]
    if run["env"] != LIFT:
        return curve, False
    if overall or run["success_air"] is None:
        return curve, True
    return dataclasses.replace(curve, success=run["success_air"]), False


def lacks_air(runs: Sequence[dict | None]) -> bool:
    """Whether a nicol_lift run among `runs` lacks `report.AIR`: then all of them are judged on overall success."""
    return any(run is not None and run["env"] == LIFT and run["success_air"] is None for run in runs)


def common_budget(runs: Sequence[dict | None]) -> int:
    """The epochs arms compared with each other are judged over: the smallest of their budgets (`protocol.budget`),
    each longer arm cut to it; 0 where none exists."""
    return min((protocol.budget(run) for run in runs if run is not None), default=0)


def cell_budget(task: str, run: dict) -> int:
    """The epochs a cell of the curves grid is judged over: its task's budget (`protocol.paper_epochs`), the same for
    every agent, or for a task without one the run's own (`protocol.budget`). A longer run is cut to it."""
    return protocol.paper_epochs().get(task) or protocol.budget(run)


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

    # the comparisons' side: every arm on one measure (all nicol_lift runs on overall success where one lacks
    # `report.AIR`) over its task's budget (`cell_budget`)
    figures: dict[tuple[str, str], Figures]  # (task, agent) -> `seed_figures` of its `judged_curve`
    budgets: dict[tuple[str, str], float]  # (task, agent) -> its run's last env steps per seed
    overall: tuple[str, ...]  # the agents whose nicol_lift run is so judged on overall success
    # the learned side: each run alone, on its own best measure (air goals where it has them)
    above: dict[tuple[str, str], np.ndarray]  # (task, agent) -> per seed, clearly above its floor (`learned_seeds`)
    floors: dict[tuple[str, str], float]  # (task, agent) -> the floor its curve is tested against
    final: dict[tuple[str, str], np.ndarray]  # (task, agent) -> each seed's final success on that measure
    learned_overall: tuple[str, ...]  # the agents whose nicol_lift run lacks `report.AIR`


def learned_floor(floors: report.Floors, task: str, overall: bool) -> tuple[float, float, float] | None:
    """(The floor a run's judged curve is shown against, the value its seeds are tested against, the share of eval
    episodes it counts): the task's floor over all goals (`report.load_floors`; tested against its upper bound,
    `report.Floor.bound`); on nicol_lift over air goals the larger of that subset's floor and what a policy that
    never lifts scores there (`LIFT_NEVER`: lifting is the skill), or, judged on overall success, the floor over all
    goals. None where results/floors lacks the task."""
    found = floors.get(task, {})
    if task != LIFT or overall:
        return (found["all"].value, found["all"].bound, 1.0) if "all" in found else None
    if "air" not in found:
        return None
    air = found["air"]
    return max(air.value, LIFT_NEVER), max(air.bound, LIFT_NEVER), air.share


def grid_figures(runs: dict[tuple[str, str], dict | None], last_n: int, floors: report.Floors) -> Grid:
    """The `Grid` of the runs that exist; `above` and `floors` only where the task's floor is known."""
    figures, budgets, overall, above, tested, final, own_overall = {}, {}, [], {}, {}, {}, []
    lift_overall = lacks_air(list(runs.values()))
    for key, run in runs.items():
        if run:
            budget = cell_budget(key[0], run)
            own, fallback = judged_curve(run)  # the run alone; compared, on overall success where an arm lacks air
            curve, compared_fallback = judged_curve(run, True) if lift_overall else (own, fallback)
            own, curve = own.first(budget), curve.first(budget)
            figures[key], budgets[key] = seed_figures(curve, last_n), float(curve.env_steps[-1])
            overall += [key[1]] * compared_fallback
            final[key], own_overall = report.final_per_seed(own, last_n), own_overall + [key[1]] * fallback
            if (floor := learned_floor(floors, key[0], fallback)) is not None:
                tested[key] = floor[0]
                above[key] = report.seeds_above(own.success, protocol.eval_episodes(run) * floor[2], floor[1], last_n)
    return Grid(figures, budgets, tuple(dict.fromkeys(overall)), above, tested, final,
                tuple(dict.fromkeys(own_overall)))


def grid_gaps(runs: dict[tuple[str, str], dict | None], agents: Sequence[str]) -> list[str]:
    """Why the cells of `agents` cannot measure a claim (`gap`): the runs of a claim about those agents alone, so
    that a missing cell of another agent (the λ = 0 ablation's) leaves it measured."""
    found = [gap(f"{t}/{a}", run, cell_budget(t, run) if run else 0) for (t, a), run in runs.items() if a in agents]
    return [g for g in found if g]


def air_note(overall: Sequence[str]) -> str:
    """The rule's words on how nicol_lift is judged, naming the runs without `report.AIR` (judged on overall
    success instead)."""
    note = f"on {LIFT}, success over air goals ({report.AIR})"
    return note + (f"; its runs without that column ({', '.join(overall)}) on overall success" if overall else "")


def learned_rule(last_n: int, overall: Sequence[str]) -> str:
    """The words of the learned checks (`learns_claims`)."""
    return (f"a run has learned its task when every seed is clearly above the task's floor (what a policy that does "
            f"nothing scores, results/floors; {air_note(overall)}, whose floor is the larger of the air goals' and "
            f"{LIFT_NEVER}, what a policy that slides but never lifts scores there): a one-sided binomial test of the "
            f"seed's successes in its last {last_n} epochs' eval episodes against the floor (its estimate's upper 95 % "
            f"bound), Holm over the run's "
            f"seeds, α = {ALPHA}; it has failed when no seed is; a task without a floor is not measured")


def learns_claims(measured: Grid, runs: dict[tuple[str, str], dict | None], last_n: int,
                  stale: set[str]) -> list[Claim]:
    """Claim (a), first part: the BidAL agents learn every task, the visual baseline none (`learned_rule`)."""
    tasks, rows = set(protocol.paper_tasks()), []
    for name, agents, learns in ((f"(a) the BidAL agents ({', '.join(BIDAL)}) learn every task", BIDAL, True),
                                 (f"(a) the visual baseline ({VISUAL}) learns no task", (VISUAL,), False)):
        cells = [key for key in measured.figures if key[1] in agents]
        gaps = grid_gaps(runs, agents) + [f"{t} has no floor (python -m experiments.probes.floors)"
                                          for t in sorted({k[0] for k in cells} - {k[0] for k in measured.above})]
        checks = []
        for key in cells:
            above = measured.above.get(key)
            learned, failed = above is not None and above.all(), above is not None and not above.any()
            checks.append(UNCLEAR if not (learned or failed) else FAVOURS if learned == learns else AGAINST)
        learned = sum(bool(measured.above.get(k, np.zeros(1, bool)).all()) for k in cells)
        final = {key: measured.final[key] for key in cells}
        pick = (min if learns else max)(cells, key=lambda k: final[k].mean(), default=None)
        ours = "—" if pick is None else (
            f"{'lowest' if learns else 'highest'}: {pick[1]} on {pick[0]} {figure(final[pick])} (floor "
            f"{measured.floors[pick]:.3f}, {int(measured.above[pick].sum())} of {final[pick].size} seeds above it)"
            if pick in measured.above else f"{'lowest' if learns else 'highest'}: {pick[1]} on {pick[0]} "
            f"{figure(final[pick])} (floor not computed)")
        ours += "" if pick is None else f"; {learned} of {len(cells)} runs learned"
        paper = "learn all tasks (Fig. 4)" if learns else "fails to learn any task (Fig. 4)"
        rows.append(Claim(name, ours, paper, judged(checks or [UNCLEAR], gaps, tasks, stale),
                          learned_rule(last_n, measured.learned_overall)))
    return rows


def learning_claims(runs: dict[tuple[str, str], dict | None], last_n: int, stale: set[str],
                    floors: report.Floors) -> list[Claim]:
    """Claim (a) from the curves grid: who learns (`learns_claims`), then OURS against its pre-registered
    comparisons (`best_claims`, `lifting_claims`), and the added arms' rows."""
    measured = grid_figures(runs, last_n, floors)
    rows = learns_claims(measured, runs, last_n, stale)
    rows += best_claims(measured, grid_gaps(runs, (OURS, *PAPER_BASELINES)), stale, floors)
    rows += [added_claim(measured, other, grid_gaps(runs, (OURS, other)), stale, floors) for other in ADDED]
    return [*rows, lifting_claim(measured, grid_gaps(runs, (OURS, *PAPER_BASELINES)), stale, last_n)]


def measure_values(measured: Grid, name: str, share: bool) -> dict[tuple[str, str], np.ndarray]:
    """(task, agent) -> each seed's `name`, env steps as a share of the run's budget where `share`."""
    steps = name not in (FINAL, AUC)
    return {key: f[name][0] / (measured.budgets[key] if share and steps else 1.0)
            for key, f in measured.figures.items()}


@dataclasses.dataclass(frozen=True)
class Compared:
    """OURS against one agent in one measure over tasks (`compared`)."""

    other: str
    measure: str
    diff: stats.Difference
    ceiling: bool  # a success measure where both arms are within CEILING of 1
    text: str


def compared(measured: Grid, tasks: Sequence[str], other: str, name: str, share: bool,
             weights: Sequence[float] | None = None) -> Compared:
    """OURS − `other` in measure `name` over `tasks` (`stats.welch_difference`: the mean over tasks by default, or
    the contrast `weights`), whether it is at the ceiling (both arms' figure ≥ 1 − CEILING: their means over the
    tasks, or with `weights` on the first task), and its text (censored seeds named)."""
    values = measure_values(measured, name, share)
    diff = stats.welch_difference([values[t, OURS] for t in tasks], [values[t, other] for t in tasks], weights)
    success = name in (FINAL, AUC)
    focus = tasks[:1] if weights is not None else tasks
    means = [np.mean([values[t, a].mean() for t in focus]) for a in (OURS, other)]
    ceiling = success and min(means) >= 1.0 - CEILING
    figures = measured.figures
    censored = sum(int(figures[t, a][name][1].sum()) for t in tasks for a in (OURS, other))
    seeds = sum(figures[t, a][name][1].size for t in tasks for a in (OURS, other))
    label = f"{name} (share of the budget)" if share and not success else name
    text = f"{label} {difference_text(diff, 3 if success or share else 0)}"
    text += f" ({censored} of {seeds} seeds censored)" if censored else ""
    return Compared(other, name, diff, ceiling, text + (" at the ceiling" if ceiling else ""))


def comparison_text(primary: Compared, check_: str, p: float, secondary: Sequence[Compared]) -> str:
    """"vs OTHER: AUC +d [l, h], Holm p = …: favours; reported: …"."""
    reported = "; ".join(c.text for c in secondary)
    p_text = "" if primary.ceiling else f", Holm p = {p:.3g}"
    return f"vs {primary.other}: {primary.text}{p_text} ({check_}); reported, not deciding: {reported}"


def floors_text(floors: report.Floors, tasks: Sequence[str], overall: bool = False) -> str:
    """"floors: planar_reach 0.008, …" of `tasks` (nicol_lift's over air goals, or over all goals where its runs are
    judged on `overall` success)."""
    subset = {LIFT: "all" if overall else "air"}
    return "floors: " + ", ".join(f"{t} {report.floor_value(floors, t, subset.get(t, 'all'))}" for t in tasks)


def comparisons(measured: Grid, tasks: Sequence[str], others: Sequence[str], share: bool,
                weights: Sequence[float] | None = None) -> tuple[list[str], list[str]]:
    """(checks, texts): OURS against each of `others` with `PRIMARY` deciding (Holm over `others`, the comparisons
    at the ceiling apart) and the other `MEASURES` reported; over `tasks` (the mean, or the contrast `weights`)."""
    primaries = [compared(measured, tasks, o, PRIMARY, share, weights) for o in others]
    diffs, ceilings = [c.diff for c in primaries], [c.ceiling for c in primaries]
    checks, adjusted = holm_checks(diffs, True, ceilings), holm_deciding(diffs, ceilings)
    texts = [comparison_text(c, k, adjusted.get(i, np.nan), [compared(measured, tasks, c.other, m, share, weights)
                                                              for m in MEASURES if m != PRIMARY])
             for i, (c, k) in enumerate(zip(primaries, checks))]
    return checks, texts


def comparison_rule(what: str, others: Sequence[str]) -> str:
    """The words of a `comparisons` claim."""
    holm = f", Holm over the {len(others)} comparisons" if len(others) > 1 else ""
    return (f"pre-registered: {OURS} against {' and against '.join(others)}; primary measure {PRIMARY} (each seed's "
            f"mean success over all epochs: learning speed over the whole budget), {what}; Welch's 95 % t interval "
            f"and p over seeds{holm}; favours when p < {ALPHA} and {OURS}'s {PRIMARY} is larger, against when p < "
            f"{ALPHA} and smaller; a measure where both arms are within {CEILING} of 1 is at the ceiling and does "
            "not decide; final success and env steps to 0.5 and 0.9 (a seed that never gets there counts the run's "
            "budget: censored) are reported, not deciding")


def best_claims(measured: Grid, gaps: list[str], stale: set[str], floors: report.Floors) -> list[Claim]:
    """Claim (a), "best overall" against the paper's baselines (the mean over tasks) and "most clearly on lifting"
    (the contrast of its margin on nicol_lift against its mean margin on the other tasks)."""
    figures = measured.figures
    names = ((f"(a) {OURS} is best overall", "best overall (Fig. 4)"),
             (f"(a) {OURS} leads most clearly on {LIFT}", "especially on lifting (Fig. 4)"))
    tasks = [t for t in protocol.paper_tasks() if all((t, a) in figures for a in (OURS, *PAPER_BASELINES))]
    if not tasks:
        why = f"{NOT_MEASURED}: no {OURS} run beside the paper's baselines' on the same tasks"
        return [Claim(c, "—", p, why, "") for c, p in names]
    checks, texts = comparisons(measured, tasks, PAPER_BASELINES, share=True)
    overall = Claim(
        names[0][0] + f" (against the paper's baselines, {' and '.join(PAPER_BASELINES)})",
        "mean over tasks: " + " / ".join(texts) + f"; {floors_text(floors, tasks, bool(measured.overall))}",
        names[0][1],
        judged(checks, gaps, set(tasks), stale),
        comparison_rule("the mean over tasks (env steps as a share of each run's budget)", PAPER_BASELINES)
        + f"; {air_note(measured.overall)}")
    others = [t for t in tasks if t != LIFT]
    if LIFT not in tasks or not others:
        return [overall, Claim(names[1][0], "—", names[1][1], f"{NOT_MEASURED}: {LIFT} or another task missing", "")]
    order = [LIFT, *others]
    checks, texts = comparisons(measured, order, LIFT_BASELINES, share=True,
                                weights=[1.0, *([-1.0 / len(others)] * len(others))])
    lift = Claim(
        names[1][0], f"{LIFT} margin − mean margin on {', '.join(others)}: " + " / ".join(texts)
        + f"; {floors_text(floors, order, bool(measured.overall))}", names[1][1],
        judged(checks, gaps, set(tasks), stale),
        comparison_rule(f"its margin on {LIFT} less its mean margin on the other tasks (a contrast of the tasks' "
                        "means; the ceiling judged on nicol_lift; against the paper's baseline that learns the "
                        "tasks: against visual_baseline, which learns next to nothing anywhere, the margin would be "
                        f"{OURS}'s own level)", LIFT_BASELINES)
        + f"; {air_note(measured.overall)}")
    return [overall, lift]


def added_claim(measured: Grid, other: str, gaps: list[str], stale: set[str], floors: report.Floors) -> Claim:
    """An added arm's row (not in the paper): OURS against `other` (multimodal_baseline; the λ = 0 ablation), the
    mean over the tasks both ran, `PRIMARY` deciding."""
    tasks = [t for t in protocol.paper_tasks() if (t, OURS) in measured.figures and (t, other) in measured.figures]
    what = "the λ = 0 ablation: where a gain comes from" if other == ABLATION else "the multimodal baseline"
    name = f"(a, added arm: {what}) {OURS} learns faster than {other}"
    paper = "not tested (the paper has no λ = 0 agent)" if other == ABLATION else \
        "not compared in the paper (its baselines are proprio and visual)"
    if not tasks:
        return Claim(name, "—", paper, f"{NOT_MEASURED}: no {OURS} run beside an {other} run", "")
    checks, texts = comparisons(measured, tasks, (other,), share=True)
    return Claim(name, f"mean over tasks: {texts[0]}; {floors_text(floors, tasks, bool(measured.overall))}", paper,
                 judged(checks, gaps, set(tasks), stale),
                 comparison_rule("the mean over tasks (env steps as a share of each run's budget)", (other,))
                 + f"; {air_note(measured.overall)}")


def lifts(final_air: np.ndarray, overall: bool) -> int:
    """How many seeds lift: final success over air goals ≥ `LIFTS`, or, judged on overall success (a run without
    `report.AIR`), overall ≥ `LIFTS_OVERALL`, which implies the former when half the goals lie in the air."""
    return int((final_air >= LIFTS_OVERALL).sum()) if overall else protocol.seeds_that_lift(final_air)


def lifting_rule(last_n: int, others: Sequence[str], protocol_name: str) -> str:
    """The words of a lifting-seeds claim."""
    holm = f", Holm over the {len(others)} comparisons" if len(others) > 1 else ""
    return (f"{protocol_name}; a seed lifts when its success over air goals over its last {last_n} epochs is ≥ "
            f"{LIFTS} (runs without {report.AIR}: overall success ≥ {LIFTS_OVERALL}); pre-registered: Fisher's exact "
            f"test (two-sided) of {OURS}'s lifting seeds against those of {' and of '.join(others)}{holm}: favours "
            f"when p < {ALPHA} and {OURS}'s share is larger, against when p < {ALPHA} and smaller; intervals: "
            "Wilson 95 % of each share")


def seeds_lifting(final: dict[str, np.ndarray], overall: Sequence[str], ours: str, others: Sequence[str],
                  ) -> tuple[list[str], str]:
    """(checks, text) of `ours`'s lifting seeds against each of `others` (agent -> final air success per seed),
    Fisher's exact test, Holm over `others`."""
    counted_seeds = {a: (lifts(v, a in overall), v.size) for a, v in final.items()}
    (k, n) = counted_seeds[ours]
    p = [stats.fisher_p(k, n, *counted_seeds[o]) for o in others]
    adjusted = stats.holm(p)
    checks = [UNCLEAR if q >= ALPHA else FAVOURS if k / n > counted_seeds[o][0] / counted_seeds[o][1] else AGAINST
              for o, q in zip(others, adjusted)]
    share = "; ".join(f"{a} {h}/{m} {stats.interval_text(*stats.wilson_interval(h, m))}"
                      for a, (h, m) in counted_seeds.items())
    tests = "; ".join(f"Fisher vs {o}: p = {q:.3g} (Holm {a:.3g})" for o, q, a in zip(others, p, adjusted))
    return checks, f"lifting seeds: {share}; {tests}"


def lifting_claim(measured: Grid, gaps: list[str], stale: set[str], last_n: int) -> Claim:
    """Claim (a) on lifting under held starts (the curves grid): OURS's seeds that lift against the paper's
    baselines'."""
    name = f"(a) more of {OURS}'s seeds lift than of the paper's baselines (held starts)"
    paper = "especially on lifting (Fig. 4)"
    rule = lifting_rule(last_n, PAPER_BASELINES, "the curves grid, HER's held starts")
    agents = [a for a in AGENTS if (LIFT, a) in measured.figures]
    if OURS not in agents or not set(PAPER_BASELINES) <= set(agents):
        return Claim(name, "—", paper, f"{NOT_MEASURED}: no {OURS} run beside the paper's baselines' on {LIFT}", rule)
    final = {a: measured.figures[LIFT, a][FINAL][0] for a in agents}
    checks, text = seeds_lifting(final, measured.overall, OURS, PAPER_BASELINES)
    return Claim(name, text, paper, judged(checks, gaps, {LIFT}, stale), rule)


def plain_claims(plain_dir: str, last_n: int, stale: set[str]) -> list[Claim]:
    """Lifting without held starts (the plain protocol, `--exploration-starts 0`; PLAIN/nicol_lift/<agent>, as
    `python -m experiments.paper.curves --tasks nicol_lift --exploration-starts 0` writes it): OURS, and the
    multimodal baseline as an added arm, each against proprio_baseline's lifting seeds. A run that is not of the
    plain protocol (its config's exploration_starts ≠ 0) is refused as missing."""
    loaded = load_grid(plain_dir, (LIFT,))
    held = [f"{LIFT}/{a} ({plain_dir}) is not of the plain protocol" for (_, a), run in loaded.items()
            if run is not None and run["config"].get("train", {}).get("exploration_starts") != 0]
    runs = {key: None if run is None or any(f"/{key[1]} " in h for h in held) else run for key, run in loaded.items()}
    rule_name = f"{plain_dir}/{LIFT}, the plain protocol (no held starts, `--exploration-starts 0`)"
    rows = []
    for ours, added in ((OURS, ""), ("multimodal_baseline", "added arm: ")):
        name = f"(a, {added}plain protocol) {ours} lifts where {PROPRIO} cannot"
        pair = [runs[LIFT, a] for a in (ours, PROPRIO)]
        budget = common_budget(pair)
        gaps = [g for a in (ours, PROPRIO) if (g := gap(f"{LIFT}/{a} ({plain_dir})", runs[LIFT, a], budget))]
        gaps = [h for h in held if f"/{ours} " in h or f"/{PROPRIO} " in h] or gaps
        rule = lifting_rule(last_n, (PROPRIO,), rule_name).replace(f"{OURS}'s", f"{ours}'s")
        paper = "especially on lifting (Fig. 4; the paper trains without held starts)" if not added else \
            "not compared in the paper"
        if runs[LIFT, ours] is None or runs[LIFT, PROPRIO] is None:
            rows.append(Claim(name, "—", paper, judged([], gaps, {LIFT}, stale), rule))
            continue
        curves = {a: judged_curve(runs[LIFT, a], lacks_air(pair)) for a in (ours, PROPRIO)}
        final = {a: report.final_per_seed(c.first(budget), last_n) for a, (c, _) in curves.items()}
        checks, text = seeds_lifting(final, [a for a, (_, o) in curves.items() if o], ours, (PROPRIO,))
        rows.append(Claim(name, text, paper, judged(checks, gaps, {LIFT}, stale), rule))
    return rows


# ----- (b) noise -------------------------------------------------------------------------------------


def noise_claims(noise_dir: str, stale: set[str], floors: report.Floors) -> list[Claim]:
    """Claim (b): steadier (`protocol.residual_spread`, "not measured" where curves still move:
    `protocol.trending`) and higher than both baselines at κ = 10 and 15 %; Holm over the 4 checks of each."""
    found, budgets = protocol.load_noise_curves(noise_dir) if os.path.isdir(noise_dir) else ({}, {})
    agents = (OURS, *BASELINES)
    gaps = [f"{a} missing" for a in agents if a not in budgets]
    gaps += [f"{a} at κ {k:.0%} missing" for a in agents if a in budgets for k in NOISE_KAPPAS if (k, a) not in found]
    budget = min((budgets[a] for a in agents if a in budgets), default=0)  # one budget for the arms compared
    found = {key: curve.first(budget) for key, curve in found.items()}
    measured = {found[k, a].run_dir: found[k, a] for a in agents for k in NOISE_KAPPAS if (k, a) in found}
    gaps += [f"{os.path.basename(run_dir)} short ({int(curve.epoch[-1])} of {budget} epochs)"
             for run_dir, curve in measured.items() if curve.epoch[-1] < budget]
    tasks = {report.load_run(run_dir)["env"] for run_dir in measured}
    floor = report.floor_text(floors, protocol.NOISE_ENV)
    moving = [f"{a} at κ {k:.0%} (slope {protocol.trend_text(found[k, a], protocol.LAST_N[k])})"
              for k in NOISE_KAPPAS for a in agents if (k, a) in found
              and protocol.trending(found[k, a], protocol.LAST_N[k])]
    measures = (
        ("steadier", "each run's residual std around its own fitted linear trend over the last N epochs",
         protocol.residual_spread, False, 1),
        ("higher", "each run's mean success over the last N epochs", report.final_per_seed, True, 0),
    )
    rows = []
    for word, what, measure, positive, column in measures:
        diffs, labels, ours, paper, ceilings = [], [], [], [], []
        for k in NOISE_KAPPAS:
            paper.append(f"{k:.0%}: " + " vs ".join(f"{protocol.PAPER[k][a][column]:.3f}" for a in agents))
            if (k, OURS) not in found:
                continue
            mine = measure(found[k, OURS], protocol.LAST_N[k])
            cells = [f"{mine.mean():.4f}"]
            for b in (b for b in BASELINES if (k, b) in found):
                theirs = measure(found[k, b], protocol.LAST_N[k])
                diffs.append(stats.welch_difference([mine], [theirs]))
                labels.append((k, b))
                ceilings.append(positive and min(mine.mean(), theirs.mean()) >= 1.0 - CEILING)  # a success measure
                cells.append(f"− {b} {difference_text(diffs[-1], 4)}" + (" at the ceiling" if ceilings[-1] else ""))
            ours.append(f"{k:.0%}: " + "; ".join(cells))
        checks, adjusted = holm_checks(diffs, positive, ceilings), holm_deciding(diffs, ceilings)
        ours_text = " / ".join(ours) or "—"
        if adjusted:
            ours_text += "; Holm p: " + ", ".join(f"{labels[i][0]:.0%} {labels[i][1]} {q:.3g}"
                                                  for i, q in adjusted.items())
        ours_text += f"; {protocol.NOISE_ENV} {floor}"
        row_gaps = gaps + ([f"curves still move over the window ({'; '.join(moving)})"] if moving and not positive
                           else [])
        rule = (f"per κ and baseline: {OURS} − baseline over runs of {what} (N = "
                f"{', '.join(str(protocol.LAST_N[k]) for k in NOISE_KAPPAS)}), Welch's 95 % t interval and p, Holm "
                f"over the {2 * len(BASELINES)} checks: favours when p < {ALPHA} and {OURS}'s is "
                f"{'larger' if positive else 'smaller'}")
        if positive:
            rule += f"; a check where both arms are within {CEILING} of 1 is at the ceiling and does not decide"
        else:
            rule += ("; not measured while an agent's curve still moves over the window (the Student-t interval "
                     "over its runs of their fitted slopes excludes 0, and the mean slope moves success by at least "
                     f"{protocol.MIN_MOVE} over the window): a spread around a climb is the climb's")
        rows.append(Claim(
            f"(b) under 10 and 15 % noise {OURS}'s success is {word} than both baselines'", ours_text,
            " / ".join(paper) + f" ({', '.join(agents)}; Table II " + ("±, \"mean standard deviation\")" if column
                                                                          else "means)"),
            judged(checks or [UNCLEAR], row_gaps, tasks, stale), rule))
    return rows


# ----- (c) transfer ----------------------------------------------------------------------------------


def transfer_claims(transfer_dir: str, stale: set[str], floors: report.Floors) -> list[Claim]:
    """Claim (c): a larger AUC from nicol_slide's representation than from scratch (primary), env steps to each of
    `protocol.THRESHOLDS` reported."""
    runs = {name: grid.loaded(os.path.join(transfer_dir, name)) for name in ("transfer", "scratch", "source")}
    budget = common_budget([runs["transfer"], runs["scratch"]])
    gaps = [g for name in ("transfer", "scratch") if (g := gap(name, runs[name], budget))]
    tasks = {run["env"] for run in runs.values() if run} | ({protocol.SOURCE_ENV} if runs["transfer"] else set())
    paper = "learns faster with the slide representation (Fig. 6; no figure given)"
    name = f"(c) reduced lift learns faster from {protocol.SOURCE_ENV} (transfer − scratch)"
    rule = (f"primary measure {PRIMARY} (each seed's mean success over all epochs), transfer − scratch over seeds, "
            f"Welch's 95 % t interval: favours when it lies above 0, against when below; env steps to "
            f"{' and '.join(f'{t:g}' for t in protocol.THRESHOLDS)} reported, not deciding; the ceiling as in (a)")
    if runs["transfer"] is None or runs["scratch"] is None:
        return [Claim(name, "—", paper, judged([], gaps, tasks, stale), rule)]
    arms = {arm: protocol.seed_measures(report.curves([runs[arm]])[0].first(budget)) for arm in ("transfer", "scratch")}
    texts, checks = [], []
    for key, (a, a_cut) in arms["transfer"].items():
        b, b_cut = arms["scratch"][key]
        diff, digits = stats.welch_difference([a], [b]), 3 if key == PRIMARY else 0
        censored = a_cut.sum() + b_cut.sum()
        note = f" ({censored} of {a.size + b.size} seeds censored at their run's env steps)" if censored else ""
        ceiling = key == PRIMARY and min(a.mean(), b.mean()) >= 1.0 - CEILING
        texts.append(f"{key} {a.mean():,.{digits}f} − {b.mean():,.{digits}f} = {difference_text(diff, digits)}{note}"
                     + (" (primary)" if key == PRIMARY else ""))
        if key == PRIMARY:
            checks.append(check(diff, diff.p, True, ceiling))
    target = runs["transfer"]["env"]
    floor = report.floor_text(floors, LIFT if target.startswith(LIFT) else target)
    return [Claim(name, "; ".join(texts) + f"; {target} over all goals, {floor}", paper,
                  judged(checks, gaps, tasks, stale), rule)]


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


def time_report(experiments: dict[str, list[dict]], old: set[str], root: str = report.RESULTS) -> str:
    """What the runs behind the claims held, for the runs on today's physics (those whose folders are in `old`, on
    other physics, `on_other_physics`, apart): the machine time, GPU time the runs held (`report.machine_shares`:
    wall time × the machine's GPUs, runs that shared a GPU counted once, by the experiments' figures.json records
    under `root`), per experiment (name -> its runs, `runs_below`) and in all; beside it, labelled, the summed
    process time (each run's last `wall_time_with_compile`, or `wall_time` where metrics.csv predates it), per
    machine as config.json records it."""
    groups = report.gpu_sharing(root) if os.path.isdir(root) else []
    today = {name: [run for run in runs if run["dir"] not in old] for name, runs in experiments.items()}
    other = [run for runs in experiments.values() for run in runs if run["dir"] in old]
    counted_runs = [run for runs in today.values() for run in runs]
    # each run's part of the time its group held, worked out over all experiments: a group split between two
    # experiments counts once in all, and its parts add up to it
    shares = report.machine_shares(counted_runs, root, groups)
    per_experiment, per_machine, without_compile = [], {}, 0
    for name, runs in today.items():
        held, summed = sum(shares[run["dir"]] for run in runs), sum(report.last_time(run)[0] for run in runs)
        per_experiment.append(f"{name} {hours(held)} ({count(len(runs), 'run')}; processes {hours(summed)})")
        for run in runs:
            seconds, with_compile = report.last_time(run)
            without_compile += not with_compile
            key = " then ".join(run["config"].get("hardware") or ["not recorded"])
            per_machine[key] = per_machine.get(key, 0.0) + seconds
    held, summed = sum(shares.values()), sum(report.last_time(run)[0] for run in counted_runs)
    machines = "; ".join(f"{machine}: {hours(seconds)}" for machine, seconds in sorted(per_machine.items()))
    return (f"Machine time of the runs behind these claims, on today's physics: {hours(held)} of GPU time held "
            f"({', '.join(per_experiment)}). Machine time is wall time × the GPUs of the processes' machine (of a "
            "run resumed on several machines, the largest), runs that shared a GPU counted once: config.json and "
            "metrics.csv record neither start times nor neighbours, so each experiment's figures.json records which "
            "runs trained k at a time on one GPU (\"gpu_sharing\"), and such a group counts max(its summed time / k, "
            "its longest run), shared by its runs in proportion to their times (a group whose runs lie in several "
            "experiments counts once in all), a run in no group its own time. "
            f"Summed process time, for comparison: {hours(summed)} (per machine, as config.json records it: "
            f"{machines or 'none'}), each run's last `wall_time_with_compile`: training and compiling, summed over "
            "its processes"
            + (f"; runs older than that column ({without_compile}) count their `wall_time`, compiling not counted"
               if without_compile else "")
            + (f". Runs on other physics, not counted: {hours(sum(report.last_time(r)[0] for r in other))} of process "
               f"time ({count(len(other), 'run')})." if other else ". No run is on other physics."))


def claims_report(curves_dir: str, noise_dir: str, transfer_dir: str, plain_dir: str, stale: set[str],
                  last_n: int, command: str, floors: report.Floors) -> tuple[str, str]:
    """(results/claims.md's text, the README's block: `readme_block`)."""
    folders = (curves_dir, noise_dir, transfer_dir, plain_dir)
    runs = {folder: runs_below(folder) for folder in folders}
    old = {run["dir"] for run in on_other_physics([run for found in runs.values() for run in found])}
    other = {folder: per_task([run for run in found if run["dir"] in old]) for folder, found in runs.items()}
    rows = [*learning_claims(load_grid(curves_dir), last_n, stale | set(other[curves_dir]), floors),
            *plain_claims(plain_dir, last_n, stale | set(other[plain_dir])),
            *noise_claims(noise_dir, stale | set(other[noise_dir]), floors),
            *transfer_claims(transfer_dir, stale | set(other[transfer_dir]), floors)]
    found = "; ".join(f"{folder}: {counted(tasks)}" for folder, tasks in other.items() if tasks)
    times = time_report({"learning curves": runs[curves_dir], "lifting, plain protocol": runs[plain_dir],
                         "noise": runs[noise_dir], "transfer": runs[transfer_dir]}, old)
    text = "\n".join([
        "# The paper's three claims, measured",
        "",
        f"From the run folders {curves_dir}, {plain_dir}, {noise_dir} and {transfer_dir}, and the tasks' floors in "
        f"{report.FLOORS} (what a policy that does nothing scores: `python -m experiments.probes.floors`).",
        "",
        "Method, fixed before reading the runs (experiments/paper/claims.py). Every claim names its comparison: "
        f"Fig. 4's are {OURS} against the paper's baselines ({' and '.join(PAPER_BASELINES)}); "
        f"{' and '.join(ADDED)} (λ = 0) are our added arms, each on its own row. Every comparison of learning speed "
        f"has one primary measure, {PRIMARY}; final success and env steps to 0.5 and 0.9 are reported and do not "
        f"decide. The paper's \"especially on lifting\" is tested three ways, each its own pre-registered row with its "
        "own primary measure, not combined: the AUC contrast of the margin on nicol_lift, and the lifting seeds under "
        "held starts and under the plain protocol (Fisher's exact test). Arms compared read one measure over the same "
        f"epochs: their budget, a longer run cut to it; on "
        f"{LIFT} success over air goals, or overall success for all where one lacks it. Where several checks "
        f"decide one claim, Holm's correction holds them at α = {ALPHA}. A success "
        f"measure where both arms are within {CEILING} of 1 is at the ceiling and does not decide. A figure's "
        "interval is Student-t over seeds (clipped to [0, 1]); a difference's is Welch's t over seeds "
        "(`experiments.stats.welch_difference`): with 5 seeds an arm a percentile bootstrap covers about 87 % "
        "where it claims 95, Welch's interval 95 % within 2.5 points on normal, bounded and skewed per-seed "
        "figures (success rates near 1, Beta, exponential; tests/experiments/test_stats.py simulates it). "
        "\"Learned\": every seed clearly above its task's floor (a one-sided binomial test, against the floor "
        "estimate's upper 95 % bound, of its last "
        f"{last_n} epochs' eval episodes, Holm over the run's seeds). Verdicts: every deciding check favours: "
        "reproduced; none favours and one is against (for a comparison: its primary measure's interval lies "
        "against the claim): reversed; otherwise not reproduced; a run missing or short (of epochs or of its "
        "planned seeds), or a steadiness measured on curves that still climb: not measured.",
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
    parser.add_argument("--plain", default=os.path.join("results", f"curves-{grid.PLAIN}"), help="the curves "
                        "grid's folder of nicol_lift under the plain protocol (`--exploration-starts 0`)")
    parser.add_argument("--floors", default=report.FLOORS, help="the folder of the tasks' floors "
                        "(python -m experiments.probes.floors)")
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
    options = [f"--curves {args.curves}", f"--noise {args.noise}", f"--transfer {args.transfer}"]
    options += [f"--plain {args.plain}"] * (args.plain != build_parser().get_default("plain"))
    options += [f"--floors {args.floors}"] * (args.floors != report.FLOORS) + [f"--out {args.out}"]
    options += [f"--stale {args.stale}"] * bool(args.stale) + [f"--last-n {args.last_n}"] * (args.last_n != 10)
    options += [f"--readme {args.readme}"] * bool(args.readme)
    try:
        previous = previous_section(args.previous or args.out, start=bool(args.previous))
        text, block = claims_report(args.curves, args.noise, args.transfer, args.plain, stale, args.last_n,
                                    " ".join([PROG, *options]), report.load_floors(args.floors))
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
