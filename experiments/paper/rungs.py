"""The pixel agents' ladder on nicol_slide (`experiments.paper.ladder`): its rungs and cells, and the tables read
from its run folders and probe file, which `experiments.paper.results_docs` renders too. The ladder's command trains
and probes; this module reads and writes nothing of its own.
"""

from __future__ import annotations

import json
import os
from typing import Any, NamedTuple, Sequence

import numpy as np

from experiments import report
from experiments.paper import grid, protocol
from experiments.paper.grid import Arm
from experiments.paper.protocol import DEFAULT_SEED, paper_epochs

TASK = "nicol_slide"
DEFAULT_OUT = os.path.join("results", "ladder")
# seeds a cell: the image rung's cells are also the visual agents' 5-seed pilot on the task (the grid's seeds a
# cell); the rungs above them ask only where their column's success lands, which 3 seeds place
PILOT_SEEDS, RUNG_SEEDS = 5, 3
LAST_N = 10
CLOSE = 0.05  # a rung closes the gap when its final success is at least the top rung's less this
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
         f"pilot on the task) and {RUNG_SEEDS} of the others. Cells: final / AUC (each seed's "
         f"final). A rung closes the gap when its final is within {CLOSE} of the top rung's. Then a linear probe of "
         "the trained, frozen encoders (ridge regression from φ(s) to the true positions on held-out frames of "
         "scripted episodes), against the same architecture randomly initialised. results/ladder/table.md has the "
         "probe of every cell, of φ and of the vision branch alone.")


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


def gap_line(arms: Sequence[Arm], runs: dict[str, dict], last_n: int) -> str:
    """Per column, the first rung below the top whose finished run's final success is at least the top rung's less
    `CLOSE`, computed from the runs; what is missing where it cannot be said."""
    by_name = {arm.name: arm for arm in arms}
    parts = []
    for i, column in enumerate(COLUMNS):
        def final(rung: Rung) -> float | None:
            arm = by_name.get(f"{rung.name}/{rung.agents[i]}")
            run = runs.get(arm.name) if arm else None
            return None if run is None or run["epoch"][-1] < arm.epochs else float(finals(run, last_n).mean())

        top = final(TOP)
        if top is None:
            parts.append(f"{column}: not measured ({TOP.name}/{TOP.agents[i]}, the level to reach, is not finished)")
            continue
        measured = [(rung, f) for rung in RUNGS[:-1] if (f := final(rung)) is not None]
        closing = next(((rung, f) for rung, f in measured if f >= top - CLOSE), None)
        missing = [rung.name for rung in RUNGS[:-1] if final(rung) is None]
        if closing:
            rung, f = closing
            parts.append(f"{column}: {rung.observes} closes it ({rung.agents[i]} {f:.3f} against {top:.3f})")
        elif missing:  # a rung not finished may still close it
            parts.append(f"{column}: not measured ({', '.join(missing)} not finished); no finished rung below "
                         f"{TOP.name} closes it ({top:.3f} to reach)")
        else:
            parts.append(f"{column}: no rung below {TOP.name} closes it ({top:.3f} to reach)")
    return f"Closes the gap (final within {CLOSE} of the {TOP.name} rung's): " + "; ".join(parts) + "."


def probe_line(probes: dict) -> str:
    """The probe of the visual agents' φ, trained and randomly initialised, in one line; that it was not run."""
    image = [f"{RUNGS[0].name}/{agent}" for agent in RUNGS[0].agents]
    probed = [name for name in image if name in probes]
    if not probed:
        return f"Linear probe of the visual agents' φ: {NOT_RUN}."
    entry = probes[probed[0]]
    parts = [f"{name.split('/')[1]} {probe_summary(probes[name], 'trained', 'phi')}" for name in probed]
    parts.append(f"random init {probe_summary(entry, 'random', 'phi')}")
    return (f"Linear probe of the visual agents' φ on held-out frames ({entry['frames'][1]:,} of {entry['episodes']} "
            "scripted episodes), mean over seeds, R² per axis x, y, z (RMSE): " + "; ".join(parts) + ".")


def loaded_runs(arms: Sequence[Arm]) -> dict[str, dict]:
    return {arm.name: run for arm in arms if (run := grid.loaded(arm.run_dir))}


def docs_table(out: str) -> str:
    """docs/results.md's ladder section (`results_docs`): the success table of the runs in `out` (the default cells:
    each rung's seeds at the budget; stale runs marked), the gap line and the probe line."""
    arms = ladder_arms(RUNGS, None, DEFAULT_SEED, None, {}, out)
    runs = loaded_runs(arms)
    stale = grid.stale_runs(arms, runs, grid.physics_today({arm.given["env"] for arm in arms})) if runs else []
    lines = f"{gap_line(arms, runs, LAST_N)} {probe_line(read_probes(out))}"
    return f"{success_table(arms, runs, LAST_N, stale)}\n\n{lines}"


def table_text(arms: Sequence[Arm], runs: dict[str, dict], probes: dict, last_n: int, stale: Sequence[str],
               command: str) -> str:
    """table.md: the success table, the gap line, the stale note, the probe's table, and the command that rewrites
    it."""
    lines = [
        f"# The pixel agents' ladder on {TASK}",
        "",
        f"Final: the mean ± std over seeds of each seed's mean eval success over its last {last_n} epochs; AUC: the "
        "mean of the seed-mean success over the epochs run; in brackets each seed's final. Floor: what a policy that "
        f"does nothing scores on {TASK} (results/floors; every rung keeps the task's starts and goals); k/S above "
        f"its floor: the seeds whose successes in the last {last_n} epochs' eval episodes are clearly above it (a "
        f"one-sided binomial test, Holm over the seeds, α = {report.ALPHA}).",
        "",
        success_table(arms, runs, last_n, stale),
        "",
        gap_line(arms, runs, last_n),
        "",
        *([f"{grid.STALE} stale: {', '.join(stale)}, {grid.STALE_WHY}.", ""] if stale else []),
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
