"""The pixel agents' ladder on nicol_slide: which input closes the gap between the visual and the multimodal agents,
and so what the visual agents' encoder fails to extract.

    python -m experiments.paper.ladder [--rungs image,ee,ee_obj,proprio] [--seeds 3] [--seed 0] [--epochs N]
        [--out results/ladder] [--dry-run | --report] [--no-probe] [--probe-episodes 200] [--last-n 10]
        [--ray --gpus-per-cell 0.5 ...] [any learner or network option of experiments.run]

Rungs (`RUNGS`), each two cells, a baseline (DDPG + HER) and a BidAL agent, `--seeds` seeds each at nicol_slide's
budget (`protocol.EPOCHS`, or `--epochs`), in OUT/<rung>/<agent>:

- `image`: visual_baseline and visual_bidal on nicol_slide, as they are (the image alone);
- `ee`: multimodal_baseline and multimodal_bidal on nicol_slide_ee, whose proprio keeps only the hand's grasp point
  `ee_pos` (a labelled env variant, `envs_mjx.nicol.NicolSlideKept`): the image and the hand's position through the
  multimodal encoder;
- `ee_obj`: the same on nicol_slide_ee_obj (`ee_pos` and the cube's centre `obj_pos`): the ladder is cumulative, each
  rung adds one input to the one below;
- `proprio`: multimodal_baseline and multimodal_bidal on nicol_slide, as they are (the image and all 40 proprio
  features): the level the rungs below are measured against.

A rung closes the gap of its column when its final success (the mean over seeds of each seed's mean over its last
`--last-n` epochs) is at least the `proprio` rung's less `CLOSE`; the table names the first rung that does, or says
that none does (`gap_line`). Then the linear probe (`experiments.probes.encoder`) of every finished cell's encoder at
its latest checkpoint, and of the same architecture randomly initialised: ridge regression from φ(s), and from the
vision branch's output, to the true `obj_pos` and `ee_pos` on frames of `--probe-episodes` scripted nicol_slide
episodes, held-out episodes scored (R² and RMSE in cm per axis), into OUT/probe.json; a cell already probed at its
latest checkpoint is not probed again. The probe runs in this process after training; with `--ray` this process
keeps JAX on the CPU (the GPUs are the cells'), so the probe waits for a run of the same command without `--ray`
(every cell then done: only the probe runs). `--no-probe` skips it.

Training goes through the grid (`experiments/paper/grid.py`), as the other paper experiments: a cell whose run is at
its epochs is skipped, an interrupted one resumes from its latest checkpoint, a stale one is refused before any
trains; `--ray` (with `--gpus-per-cell`, ...) trains the cells as Ray tasks, several sharing a GPU. `--rungs` trains
only the rungs named; the results are written from every rung's runs. `--dry-run` prints the plan with its estimated
time and writes nothing; `--report` trains and probes nothing and writes only the results.

Results, from whatever runs have epochs and OUT/probe.json: OUT/table.md (per rung and agent the final success,
AUC and each seed's final, the gap line, and the probe's figures: R² and RMSE per axis, the mean over seeds), OUT/
curves.png and .csv (one panel per rung), and OUT/figures.json, the section of docs/results.md
(`python -m experiments.paper.results_docs` renders it through `docs_table`): the commands that trained or probed,
the machines the runs record, the dates and commits. Exit codes as experiments.paper.curves.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import subprocess
import sys
from typing import Any, NamedTuple, Sequence

import jax
import numpy as np

import envs_mjx
from bidal_jax.config import ConfigError, option
from bidal_jax.run import checkpoint, multihost, rundir, runfiles
from experiments import cli, cluster, report
from experiments.paper import grid
from experiments.paper.grid import Arm
from experiments.paper.protocol import DEFAULT_SEED, EPOCHS
from experiments.probes import encoder

PROG = "python -m experiments.paper.ladder"
TASK = "nicol_slide"
DEFAULT_OUT = os.path.join("results", "ladder")
DEFAULT_SEEDS = 5  # the image rung is also the visual agents' 5-seed pilot on the task
LAST_N = 10
CLOSE = 0.05  # a rung closes the gap when its final success is at least the top rung's less this
PROBE_EPISODES = 200  # scripted episodes of the probe's frames: 10,000 frames, a fifth of the episodes held out
PROBE_FILE = "probe.json"
NOT_RUN = "not run"
COLUMNS = ("baseline", "bidal")


class Rung(NamedTuple):
    """A rung: its folder name, env, the agents of its two columns (baseline, BidAL) and what they observe."""

    name: str
    env: str
    agents: tuple[str, str]
    observes: str


VISUAL, MULTIMODAL = ("visual_baseline", "visual_bidal"), ("multimodal_baseline", "multimodal_bidal")
RUNGS = (
    Rung("image", TASK, VISUAL, "image"),
    Rung("ee", "nicol_slide_ee", MULTIMODAL, "image + ee_pos"),
    Rung("ee_obj", "nicol_slide_ee_obj", MULTIMODAL, "image + ee_pos + obj_pos"),
    Rung("proprio", TASK, MULTIMODAL, "image + all proprio (the multimodal agents)"),
)
TOP = RUNGS[-1]
ABOUT = (f"What the pixel agents lack on {TASK}: the baseline (DDPG + HER) and BidAL agents with the image alone (the "
         "visual agents), then with the hand's position `ee_pos` beside it (env nicol_slide_ee, through the multimodal "
         "encoder), then with the cube's position `obj_pos` too (nicol_slide_ee_obj), then with all proprio (the "
         f"multimodal agents); {DEFAULT_SEEDS} seeds a cell at the task's budget. Cells: final / AUC (each seed's "
         f"final). A rung closes the gap when its final is within {CLOSE} of the top rung's. Then a linear probe of "
         "the trained, frozen encoders (ridge regression from φ(s) to the true positions on held-out frames of "
         "scripted episodes), against the same architecture randomly initialised. results/ladder/table.md has the "
         "probe of every cell, of φ and of the vision branch alone.")


def ladder_arms(rungs: Sequence[Rung], seeds: int, seed: int, epochs: int | None, extra: dict[str, Any],
                out: str) -> list[Arm]:
    """The ladder's cells in OUT/<rung>/<agent>, rung by rung, each `epochs` or else nicol_slide's budget."""
    return [Arm(f"{rung.name}/{agent}", {"env": rung.env, "agent": agent, "seeds": seeds, "seed": seed, **extra,
                                         "epochs": epochs or EPOCHS[TASK],
                                         "run_dir": os.path.join(out, rung.name, agent)})
            for rung in rungs for agent in rung.agents]


def build_parser() -> argparse.ArgumentParser:
    parser = grid.experiment_parser(PROG, __doc__, "every run")
    parser.add_argument("--rungs", default=",".join(r.name for r in RUNGS),
                        help=f"comma list of the rungs to train (default all: {', '.join(r.name for r in RUNGS)})")
    parser.add_argument("--agents", default=",".join(dict.fromkeys(VISUAL + MULTIMODAL)),
                        help="comma list of the agents to train of the chosen rungs (default all), e.g. one column, or "
                        "one agent a process so that two processes share a GPU")
    parser.add_argument("--seeds", type=int, default=DEFAULT_SEEDS, help="seeds of every cell, vmapped as one program")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="first random seed of every run")
    parser.add_argument("--epochs", type=int, default=None,
                        help=f"epochs of every run (default {TASK}'s budget, {EPOCHS[TASK]})")
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--dry-run", action="store_true", help="print the plan and its estimated time; write nothing")
    mode.add_argument("--report", action="store_true", help="train and probe nothing: write the results from the run "
                      f"folders and {PROBE_FILE}")
    parser.add_argument("--no-probe", action="store_true", help="train, but probe no encoder")
    parser.add_argument("--probe-episodes", type=int, default=PROBE_EPISODES,
                        help=f"scripted episodes of the probe's frames, a fifth held out (default {PROBE_EPISODES})")
    parser.add_argument("--last-n", type=int, default=LAST_N, help="epochs averaged for the final success")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


# ----- the probe ------------------------------------------------------------------------------------------------


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


def to_probe(arms: Sequence[Arm], probes: dict) -> list[Arm]:
    """The arms whose run is at its epochs with a checkpoint there, and whose probe is missing or of another
    checkpoint step."""
    found = []
    for arm in arms:
        step = checkpoint.latest_step(os.path.join(arm.run_dir, "checkpoints"))
        if step is not None and step >= arm.epochs and probes.get(arm.name, {}).get("step") != step:
            found.append(arm)
    return found


def probe_arms(arms: Sequence[Arm], out: str, episodes: int, seed: int) -> None:
    """Probe the encoders of `arms` (`to_probe`'s) and of their random initialisations (`experiments.probes.encoder`)
    on one set of frames, writing OUT/probe.json after each cell."""
    probes = read_probes(out)
    env = envs_mjx.make(TASK, render=True)
    print(f"probe: rendering the frames of {episodes} scripted {TASK} episodes", flush=True)
    frames = encoder.slide_frames(env, episodes, jax.random.PRNGKey(seed))
    train, test = encoder.split(frames.episode)
    for arm in arms:
        trained = encoder.load_encoder(arm.run_dir)
        arm_env = envs_mjx.make(arm.given["env"], render=False)
        segments = arm_env.observation_spec.segment_names
        probes[arm.name] = {
            "run_dir": arm.run_dir, "step": checkpoint.latest_step(os.path.join(arm.run_dir, "checkpoints")),
            "episodes": episodes, "frames": [int(train.sum()), int(test.sum())],
            "trained": encoder.probe(trained, frames, segments),
            "random": encoder.probe(encoder.random_encoder(trained, arm_env), frames, segments),
        }
        path = os.path.join(out, PROBE_FILE)
        with rundir.writing(path):
            runfiles.write_atomic(path, json.dumps({"cells": probes}, indent=1) + "\n")
        print(f"probe: {arm.name}: {probe_summary(probes[arm.name], 'trained', 'phi')}", flush=True)


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


def cell(arm: Arm, run: dict | None, last_n: int, stale: bool) -> str:
    """A cell: "final ± std / AUC (each seed's final)", how far an unfinished run got, † when stale; `NOT_RUN`."""
    if run is None:
        return NOT_RUN
    curve = report.curves([run], labels={run["dir"]: arm.name})[0]
    done = int(run["epoch"][-1])
    progress = "" if done >= arm.epochs else f", epoch {done} of {arm.epochs}"
    per_seed = ", ".join(f"{v:.3f}" for v in finals(run, last_n))
    return (f"{report.final_cell(curve, last_n)} / {report.normalized_auc(curve):.3f} ({per_seed}){progress}"
            + (grid.STALE if stale else ""))


def success_table(arms: Sequence[Arm], runs: dict[str, dict], last_n: int, stale: Sequence[str]) -> str:
    """Markdown, a rung a row: what its agents observe, its env, and each column's cell (`cell`)."""
    by_name = {arm.name: arm for arm in arms}
    rows = []
    for rung in RUNGS:
        cells = [by_name[f"{rung.name}/{agent}"] for agent in rung.agents if f"{rung.name}/{agent}" in by_name]
        if cells:
            rows.append([rung.observes, rung.env, *(
                f"{arm.given['agent']}: {cell(arm, runs.get(arm.name), last_n, arm.name in stale)}" for arm in cells)])
    head = ["input", "env", *(f"{column}: final / AUC (per seed)" for column in COLUMNS)]
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
        unmeasured = f" ({', '.join(missing)} not finished)" if missing else ""
        if closing:
            rung, f = closing
            parts.append(f"{column}: {rung.observes} closes it ({rung.agents[i]} {f:.3f} against {top:.3f})")
        else:
            parts.append(f"{column}: no rung below {TOP.name} closes it ({top:.3f} to reach){unmeasured}")
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
    `DEFAULT_SEEDS` seeds at the budget; stale runs marked), the gap line and the probe line."""
    arms = ladder_arms(RUNGS, DEFAULT_SEEDS, DEFAULT_SEED, None, {}, out)
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
        "mean of the seed-mean success over the epochs run; in brackets each seed's final.",
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


# ----- the record (figures.json) --------------------------------------------------------------------------------


def git_commit() -> str:
    """The checkout's short commit, "not recorded" outside a git checkout."""
    try:
        found = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                               cwd=os.path.dirname(os.path.abspath(__file__)), timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "not recorded"
    return found.stdout.strip() if found.returncode == 0 and found.stdout.strip() else "not recorded"


def machines(runs: dict[str, dict]) -> str:
    """The machines and physics engines the runs' config.json records, distinct, or `NOT_RUN`."""
    engines = {"jax": "MJX-JAX", "warp": "MuJoCo Warp"}
    found = dict.fromkeys(
        f"{' then '.join(run['config'].get('hardware') or ['machine not recorded'])}, "
        f"{' then '.join(engines.get(e, e) for e in run['config'].get('physics_engine') or ['physics not recorded'])}"
        for run in runs.values())
    return "; ".join(found) or NOT_RUN


def joined(previous: str | None, now: str) -> str:
    """`previous` (a record's "; "-joined values; None for none) with `now` added unless already there."""
    values = previous.split("; ") if previous else []
    return "; ".join(values + ([] if now in values else [now]))


def section(previous: dict | None, runs: dict[str, dict], command: str | None) -> dict:
    """The ladder's figures.json section: the previous record (none while its date is `NOT_RUN`) with `command` (this
    invocation's; None when it trained and probed nothing), today's date and this commit added; the machines of the
    runs (`machines`), `ABOUT`, and the figure where a run has epochs."""
    previous = previous if previous and previous.get("date", NOT_RUN) != NOT_RUN else {}
    record = {key: previous.get(key) for key in ("command", "date", "commit")}
    if command is not None:
        record = {"command": joined(record["command"], command),
                  "date": joined(record["date"], datetime.date.today().isoformat()),
                  "commit": joined(record["commit"], git_commit())}
    return {"part": "Learning (paper Fig. 4)", "title": "A ladder for the pixel agents", "about": ABOUT,
            "command": record["command"] or PROG, "machine": machines(runs), "date": record["date"] or NOT_RUN,
            "commit": record["commit"] or NOT_RUN, "table": "ladder", "runs": "ladder",
            **({"figure": "curves.png"} if runs else {})}


def read_section(path: str) -> dict | None:
    """The section of the ladder's figures.json at `path`; None where there is none. RunError naming a damaged one."""
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            return dict(json.load(f)[0])
    except (ValueError, KeyError, IndexError, TypeError) as err:
        raise report.RunError(f"{path}: unreadable figures file ({err})") from None


def write_results(out: str, arms: Sequence[Arm], last_n: int, today: dict[str, str | None], command: str | None,
                  regenerate: str) -> None:
    """table.md, curves.png/.csv (where a run has epochs) and figures.json in `out` (`section`)."""
    runs, probes = loaded_runs(arms), read_probes(out)
    stale = grid.stale_runs(arms, runs, today) if runs else []
    figures = os.path.join(out, "figures.json")
    found = section(read_section(figures), runs, command)
    if runs:
        rungs = {os.path.join(out, rung.name): rung.observes for rung in RUNGS}
        curves = report.curves(list(runs.values()), panel_by=lambda run: rungs[os.path.dirname(run["dir"])])
        grid.write_figure(curves, os.path.join(out, "curves"), f"{TASK}: eval success against env steps per seed")
    os.makedirs(out, exist_ok=True)
    with rundir.writing(figures):
        runfiles.write_atomic(figures, json.dumps([found], indent=2, ensure_ascii=False) + "\n")
    grid.write_table(out, table_text(arms, runs, probes, last_n, stale, regenerate))


def regenerate_command(args: argparse.Namespace, rest: Sequence[str]) -> str:
    """The command that rewrites the results from the run folders and probe.json alone."""
    parser = build_parser()
    chosen = [f"{option(name)} {getattr(args, name)}" for name in ("seeds", "seed", "epochs", "last_n", "out")
              if getattr(args, name) != parser.get_default(name)]
    return " ".join([PROG, "--report", *chosen, *map(shlex.quote, rest)])


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args, rest = build_parser().parse_known_args(argv)
    try:
        extra = grid.pass_through(rest, PROG)
        cluster.prepare_driver(args)
        multihost.initialize()
        names = cli.parse_names(args.rungs, "--rungs", "rung", tuple(r.name for r in RUNGS))
        if args.probe_episodes < 5:
            raise ConfigError(f"--probe-episodes {args.probe_episodes}: must be an integer >= 5")
        arms = grid.checked_arms(ladder_arms(RUNGS, args.seeds, args.seed, args.epochs, extra, args.out), args.last_n)
        agents = cli.parse_names(args.agents, "--agents", "agent", VISUAL + MULTIMODAL)
        chosen = [arm for arm in arms if arm.name.split("/")[0] in names and arm.given["agent"] in agents]
    except ConfigError as err:
        return cli.exit_code(err)
    code, command = 0, None
    try:
        envs = grid.make_envs(arms)
        if not args.report:
            print(grid.estimated_plan(chosen, envs, f"plan: {len(chosen)} runs"), flush=True)
            waiting = to_probe(chosen, read_probes(args.out))
            if args.dry_run:
                print("probe: none (--no-probe)" if args.no_probe else f"probe: {len(waiting)} cell(s) at their epochs "
                      f"to probe now ({args.probe_episodes} scripted episodes of frames)")
                print(grid.DRY_RUN)
                return 0
            statuses = [grid.status(arm, envs[arm.name].physics_id).state for arm in chosen]
            code = grid.train_arms(chosen, envs, args, args.out)
            # a failed or stopped grid probes nothing: run the same command again
            waiting = to_probe(chosen, read_probes(args.out)) if code == 0 and not args.no_probe else []
            if waiting and cluster.wanted(args):
                print(f"probe: {len(waiting)} cell(s) to probe: run the same command without --ray (this process keeps "
                      "JAX on the CPU under Ray)")
            elif waiting and multihost.is_main():
                probe_arms(waiting, args.out, args.probe_episodes, args.seed)
            if any(state != "done" for state in statuses) or (waiting and not cluster.wanted(args)):
                command = " ".join([PROG, *map(shlex.quote, argv)])
        if multihost.is_main():
            today = {arm.given["env"]: envs[arm.name].physics_id for arm in arms}
            write_results(args.out, arms, args.last_n, today, command, regenerate_command(args, rest))
    except cli.FAILURES as err:
        failed = cli.exit_code(err)
        return code or failed
    return code


if __name__ == "__main__":
    sys.exit(cli.command(main))
