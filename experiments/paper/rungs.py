"""The pixel agents' ladder on nicol_slide (`experiments.paper.ladder`): its rungs and cells, and the tables read
from its run folders and probe file, which `experiments.paper.results_docs` renders too. The ladder's command trains
and probes; this module reads and writes nothing of its own.
"""

from __future__ import annotations

import json
import math
import os
from typing import Any, Collection, NamedTuple, Sequence

import numpy as np

from experiments import report, stats
from experiments.paper import grid, protocol
from experiments.paper.grid import Arm
from experiments.paper.protocol import DEFAULT_SEED, paper_epochs

TASK = "nicol_slide"
DEFAULT_OUT = os.path.join("results", "ladder")
# seeds a cell: the image rung's cells are also the visual agents' 5-seed pilot on the task (the grid's seeds a
# cell); the rungs above them ask only where their column's success lands, which 3 seeds place
PILOT_SEEDS, RUNG_SEEDS = 5, 3
LAST_N = 10
# a rung closes the gap when Welch's 95 % interval of its per-seed finals less the top rung's lies at or above -CLOSE
CLOSE = 0.05
PROBE_FILE = "probe.json"
NOT_RUN = "not run"
COLUMNS = ("baseline", "bidal")
class Rung(NamedTuple):
    """A rung: its folder name, env, the agents of its two columns (baseline, BidAL), what they observe and the
    seeds of each of its cells."""

    name: str
    env: str
    agents: tuple[str, str]
    observes: str
    seeds: int = RUNG_SEEDS


VISUAL, MULTIMODAL = ("visual_baseline", "visual_bidal"), ("multimodal_baseline", "multimodal_bidal")
RUNGS = (
    Rung("image", TASK, VISUAL, "image", PILOT_SEEDS),
    Rung("ee", "nicol_slide_ee", MULTIMODAL, "image + ee_pos"),
    Rung("ee_obj", "nicol_slide_ee_obj", MULTIMODAL, "image + ee_pos + obj_pos"),
    Rung("proprio", TASK, MULTIMODAL, "image + all proprio (the multimodal agents)"),
)
TOP = RUNGS[-1]
ABOUT = (f"What the pixel agents lack on {TASK}: the baseline (DDPG + HER) and BidAL agents with the image alone (the "
         "visual agents), then with the hand's position `ee_pos` beside it (env nicol_slide_ee, through the multimodal "
         "encoder), then with the cube's position `obj_pos` too (nicol_slide_ee_obj), then with all proprio (the "
         f"multimodal agents); at the task's budget, {PILOT_SEEDS} seeds a cell of the image rung (the visual agents' "
         f"pilot on the task) and {RUNG_SEEDS} of the others. Cells: final / AUC (each seed's final). There is a gap "
         "to close when every seed of the top rung is above the task's floor and the image rung's final is more than "
         f"{CLOSE} below the top rung's; a rung closes it when Welch's 95 % interval of its per-seed finals less the "
         f"top rung's lies at or above −{CLOSE}; the gap line names the first rung that does, unless a rung below it "
         "is unfinished or stale. Then a linear probe of the trained, frozen encoders (ridge regression from φ(s) to "
         "the true positions on held-out frames of scripted episodes), against the same architecture randomly "
         "initialised. results/ladder/table.md has the probe of every cell, of φ and of the vision branch alone.")


def ladder_arms(rungs: Sequence[Rung], seeds: int | None, seed: int, epochs: int | None, extra: dict[str, Any],
                out: str) -> list[Arm]:
    """The ladder's cells in OUT/<rung>/<agent>, rung by rung, each `seeds` seeds or else its rung's, and `epochs`
    or else nicol_slide's budget."""
    return [Arm(f"{rung.name}/{agent}", {"env": rung.env, "agent": agent,
                                         "seeds": rung.seeds if seeds is None else seeds, "seed": seed, **extra,
                                         "epochs": epochs or paper_epochs()[TASK],
                                         "run_dir": os.path.join(out, rung.name, agent)})
            for rung in rungs for agent in rung.agents]



# ----- the probe's file and figures -----------------------------------------------------------------------------


def read_probes(out: str) -> dict:
    """OUT/probe.json's cells (arm name -> its probe entry); {} where the ladder has none. RunError naming a damaged
    file."""
    path = os.path.join(out, PROBE_FILE)
    if not os.path.isfile(path):
        return {}
    try:
        with open(path, encoding="utf-8") as f:
            return dict(json.load(f)["cells"])
    except (ValueError, KeyError, TypeError) as err:
        raise report.RunError(f"{path}: unreadable probe file ({err})") from None


def axes(values: list[list[float | None]], digits: int = 2) -> str:
    """Per-seed values [S][3] as their mean over seeds per axis, "x, y, z"; "—" for an axis without a value (an R² the
    probe leaves undefined: a target that hardly varies along it)."""
    columns = zip(*values)
    return ", ".join("—" if None in column else f"{np.mean(column):.{digits}f}" for column in columns)


def probe_summary(entry: dict, encoding: str, features: str) -> str:
    """One encoder's probe from one feature set: "obj_pos R² x, y, z (RMSE x, y, z cm); ee_pos ..."."""
    found = entry[encoding][features]
    return "; ".join(f"{target} R² {axes(found[target]['r2'])} ({axes(found[target]['rmse_cm'], 1)} cm)"
                     for target in found)


def probe_table(arms: Sequence[Arm], probes: dict) -> str:
    """Markdown: per probed cell, encoder (trained, random init) and feature set (φ, the vision branch alone), the
    mean over seeds of R² and RMSE (cm) per axis x, y, z, for obj_pos and ee_pos."""
    rows = []
    for arm in (a for a in arms if a.name in probes):
        entry = probes[arm.name]
        for encoding in ("trained", "random"):
            for features, named in (("phi", "φ(s)"), ("image", "vision branch")):
                found = entry[encoding][features]
                rows.append([arm.name, f"{encoding}, step {entry['step']}" if encoding == "trained" else "random init",
                             named, *(axes(found[t][k], d) for t in ("obj_pos", "ee_pos")
                                      for k, d in (("r2", 2), ("rmse_cm", 1)))])
    head = ["cell", "encoder", "features", "obj_pos R² (x, y, z)", "obj_pos RMSE (cm)", "ee_pos R² (x, y, z)",
            "ee_pos RMSE (cm)"]
    return report.markdown_table(head, rows)


# ----- the tables -----------------------------------------------------------------------------------------------


def finals(run: dict, last_n: int) -> np.ndarray:
    """Each seed's mean success over its last `last_n` epochs [S]."""
    return run["success"][-last_n:].mean(axis=0)


def cell(arm: Arm, run: dict | None, last_n: int, stale: bool, floors: report.Floors) -> str:
    """A cell: "final ± std / AUC (each seed's final), k/S above its floor" (`protocol.above_floor`), how far an
    unfinished run got, † when stale; `NOT_RUN`."""
    if run is None:
        return NOT_RUN
    curve = report.curves([run], labels={run["dir"]: arm.name})[0]
    done = int(run["epoch"][-1])
    progress = "" if done >= arm.epochs else f", epoch {done} of {arm.epochs}"
    per_seed = ", ".join(f"{v:.3f}" for v in finals(run, last_n))
    above = protocol.above_floor(run, floors, last_n)
    return (f"{report.final_cell(curve, last_n)} / {report.normalized_auc(curve):.3f} ({per_seed})"
            f"{', ' + above if above else ''}{progress}" + (grid.STALE if stale else ""))


def success_table(arms: Sequence[Arm], runs: dict[str, dict], last_n: int, stale: Sequence[str]) -> str:
    """Markdown, a rung a row: what its agents observe, its env, the task's floor (results/floors: every rung is
    nicol_slide's task) and each column's cell (`cell`)."""
    floors = report.load_floors()
    by_name = {arm.name: arm for arm in arms}
    rows = []
    for rung in RUNGS:
        cells = [by_name[f"{rung.name}/{agent}"] for agent in rung.agents if f"{rung.name}/{agent}" in by_name]
        if cells:
            rows.append([rung.observes, rung.env, report.floor_value(floors, TASK), *(
                f"{arm.given['agent']}: {cell(arm, runs.get(arm.name), last_n, arm.name in stale, floors)}"
                for arm in cells)])
    head = ["input", "env", "floor", *(f"{column}: final / AUC (per seed)" for column in COLUMNS)]
    return report.markdown_table(head, rows)


def unusable(arm: Arm | None, run: dict | None, stale: Collection[str]) -> str:
    """Why the gap line cannot use a cell: "not finished" (no run, or one short of its epochs), "stale" (`stale`:
    arm names, `grid.stale_runs`), "of one seed" (no interval); "" where it can."""
    if arm is None or run is None or run["epoch"][-1] < arm.epochs:
        return "not finished"
    if arm.name in stale:
        return "stale"
    return "of one seed" if run["success"].shape[1] < 2 else ""


def difference(rung: np.ndarray, top: np.ndarray) -> tuple[float, float, float]:
    """(difference, low, high): the mean of the rung's per-seed finals less the top rung's, with Welch's 95 %
    interval (`stats.welch_interval`); where neither cell's seeds vary (Welch's is undefined), the interval is the
    difference itself."""
    diff, low, high = stats.welch_interval(rung, top)
    return (diff, diff, diff) if math.isnan(low) else (diff, low, high)


def column_gap(i: int, arms: dict[str, Arm], runs: dict[str, dict], last_n: int, stale: Collection[str],
               floors: report.Floors) -> str:
    """The gap line's text of column `i` (`gap_line`): not measured while the top rung's cell is unusable (`unusable`)
    or the task has no floor (`protocol.seeds_above_floor`); no gap to close unless every top seed is above the
    floor and the image rung's final is more than `CLOSE` below the top's; else, scanning the rungs bottom-up,
    the first that closes it (`difference`'s low end at least −`CLOSE`), not measured where an unusable rung
    comes before it."""
    def cell_of(rung: Rung) -> tuple[Arm | None, dict | None]:
        arm = arms.get(f"{rung.name}/{rung.agents[i]}")
        return arm, runs.get(arm.name) if arm else None

    top_arm, top_run = cell_of(TOP)
    if why := unusable(top_arm, top_run, stale):
        return f"not measured ({TOP.name}/{TOP.agents[i]}, the level to reach, is {why})"
    above = protocol.seeds_above_floor(top_run, floors, last_n)
    if above is None:
        return f"not measured ({TASK} has no floor)"
    top = finals(top_run, last_n)
    if not above.all():
        return f"no gap to close ({TOP.agents[i]} {top.mean():.3f}, {above.sum()}/{above.size} seeds above its floor)"
    blocked: dict[str, list[str]] = {}  # why -> the unusable rungs below the first that closes the gap
    measured = ""  # the difference of the highest finished rung so far
    for rung in RUNGS[:-1]:
        arm, run = cell_of(rung)
        if why := unusable(arm, run, stale):
            blocked.setdefault(why, []).append(rung.name)
            continue
        final = finals(run, last_n)
        if rung is RUNGS[0] and top.mean() - final.mean() <= CLOSE:
            return f"no gap to close ({rung.agents[i]} {final.mean():.3f}, {TOP.agents[i]} {top.mean():.3f})"
        diff, low, high = difference(final, top)
        measured = f"{rung.name} − {TOP.name} {diff:+.3f} {stats.interval_text(low, high)}"
        if low >= -CLOSE:
            closes = f"{rung.agents[i]} {final.mean():.3f} against {top.mean():.3f}; {measured}"
            return (f"not measured ({unmeasured(blocked)}); the first finished rung to close it is {rung.name} "
                    f"({closes})" if blocked else f"{rung.observes} closes it ({closes})")
    reached = f"{measured}; {top.mean():.3f} to reach" if measured else f"{top.mean():.3f} to reach"
    if blocked:
        return f"not measured ({unmeasured(blocked)}); no finished rung below {TOP.name} closes it ({reached})"
    return f"no rung below {TOP.name} closes it ({reached})"


def unmeasured(blocked: dict[str, list[str]]) -> str:
    """The rungs that leave a gap not measured, by why: "ee, ee_obj not finished; image stale"."""
    return "; ".join(f"{', '.join(names)} {why}" for why, names in blocked.items())


def gap_line(arms: Sequence[Arm], runs: dict[str, dict], last_n: int, stale: Collection[str]) -> str:
    """Per column, the first rung below the top that closes the gap (`column_gap`), computed from the runs, stale
    ones (`stale`, arm names) left out as unfinished ones are; what is missing where it cannot be said."""
    by_name, floors = {arm.name: arm for arm in arms}, report.load_floors()
    parts = [f"{column}: {column_gap(i, by_name, runs, last_n, stale, floors)}" for i, column in enumerate(COLUMNS)]
    return (f"Closes the gap (there is one when every {TOP.name} seed is above the floor and the image rung's final "
            f"is more than {CLOSE} below the {TOP.name} rung's; a rung closes it when Welch's 95 % interval of its "
            f"per-seed finals less the {TOP.name} rung's lies at or above −{CLOSE}): " + "; ".join(parts) + ".")


def probe_line(probes: dict) -> str:
    """The probe of the visual agents' φ, trained and randomly initialised, in one line; that it was not run."""
    image = [f"{RUNGS[0].name}/{agent}" for agent in RUNGS[0].agents]
    probed = [name for name in image if name in probes]
    if not probed:
        return f"Linear probe of the visual agents' φ: {NOT_RUN}."
    entry = probes[probed[0]]
    parts = [f"{name.split('/')[1]} {probe_summary(probes[name], 'trained', 'phi')}" for name in probed]
    parts.append(f"random init {probe_summary(entry, 'random', 'phi')}")
    fitted, held = entry["frames"]
    scored = round(entry["episodes"] * held / (fitted + held))  # the held-out episodes: all are of one length
    return (f"Linear probe of the visual agents' φ on {held:,} held-out frames (of {scored} of {entry['episodes']} "
            f"scripted episodes; fitted on the other {fitted:,} frames), mean over seeds, R² per axis x, y, z (RMSE): "
            + "; ".join(parts) + ".")


def loaded_runs(arms: Sequence[Arm]) -> dict[str, dict]:
    return {arm.name: run for arm in arms if (run := grid.loaded(arm.run_dir))}


def docs_table(out: str) -> str:
    """docs/results.md's ladder section (`results_docs`): the success table of the runs in `out` (the default cells:
    each rung's seeds at the budget; stale runs marked), the gap line and the probe line, and the runs resumed with an
    empty replay buffer (`grid.fresh_buffer_note`)."""
    arms = ladder_arms(RUNGS, None, DEFAULT_SEED, None, {}, out)
    runs = loaded_runs(arms)
    stale = grid.stale_runs(arms, runs, grid.physics_today({arm.given["env"] for arm in arms})) if runs else []
    lines = [success_table(arms, runs, LAST_N, stale), "",
             f"{gap_line(arms, runs, LAST_N, stale)} {probe_line(read_probes(out))}", "",
             *grid.fresh_buffer_note({name: run["config"] for name, run in runs.items()})]
    return "\n".join(lines).rstrip("\n")  # the section's text ends without a blank line


def table_text(arms: Sequence[Arm], runs: dict[str, dict], probes: dict, last_n: int, stale: Sequence[str],
               command: str) -> str:
    """table.md: the success table, the gap line, the stale note, the runs resumed with an empty replay buffer
    (`grid.fresh_buffer_note`), the probe's table, and the command that rewrites it."""
    lines = [
        f"# The pixel agents' ladder on {TASK}",
        "",
        f"Final: the mean ± std over seeds of each seed's mean eval success over its last {last_n} epochs; AUC: the "
        "mean of the seed-mean success over the epochs run; in brackets each seed's final. Floor: what a policy that "
        f"does nothing scores on {TASK} (results/floors; every rung keeps the task's starts and goals); k/S above "
        f"its floor: the seeds whose successes in the last {last_n} epochs' eval episodes are clearly above it (a "
        f"one-sided binomial test against the floor estimate's upper 95 % bound, Holm over the seeds, α = "
        f"{report.ALPHA}).",
        "",
        success_table(arms, runs, last_n, stale),
        "",
        gap_line(arms, runs, last_n, stale),
        "",
        *([f"{grid.STALE} stale: {', '.join(stale)}, {grid.STALE_WHY}.", ""] if stale else []),
        *grid.fresh_buffer_note({name: run["config"] for name, run in runs.items()}),
        "## Linear probe of the encoders",
        "",
        "Ridge regression from the features of a frame to the true positions (experiments/probes/encoder.py), fitted "
        "on the frames of four fifths of the scripted episodes and scored on the others; the mean over seeds. φ(s) "
        "is what the actor and critic read (image and the cell's proprio); the vision branch is the image's part of "
        "the encoder alone. Random init: the same architecture with fixed keys and the run's normaliser.",
        "",
        probe_table(arms, probes) if probes else f"Probe: {NOT_RUN}.",
        "",
        grid.gaps(arms, runs),
        "",
        f"Regenerate from the run folders: `{command}`",
        "",
    ]
    return "\n".join(lines)
