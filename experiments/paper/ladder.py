"""The pixel agents' ladder on nicol_slide: which input closes the gap between the visual and the multimodal agents,
and so what the visual agents' encoder fails to extract.

    python -m experiments.paper.ladder [--rungs image,ee,ee_obj,proprio] [--seeds 3] [--seed 0] [--epochs N]
        [--out results/ladder] [--dry-run | --report] [--no-probe] [--probe-episodes 200] [--last-n 10]
        [--ray --gpus-per-cell 0.5 ...] [any learner or network option of experiments.run]

Rungs (`RUNGS`), each two cells, a baseline (DDPG + HER) and a BidAL agent at nicol_slide's budget
(`protocol.paper_epochs`, or `--epochs`), in OUT/<rung>/<agent>; each cell `--seeds` seeds, else its rung's
(`Rung.seeds`: 5 for the image rung, whose cells are also the visual agents' 5-seed pilot on the task, 3 for the
others):

- `image`: visual_baseline and visual_bidal on nicol_slide, as they are (the image alone);
- `ee`: multimodal_baseline and multimodal_bidal on nicol_slide_ee, whose proprio keeps only the hand's grasp point
  `ee_pos` (a labelled env variant, `envs_mjx.nicol.NicolSlideKept`): the image and the hand's position through the
  multimodal encoder;
- `ee_obj`: the same on nicol_slide_ee_obj (`ee_pos` and the cube's centre `obj_pos`): the ladder is cumulative, each
  rung adds one input to the one below;
- `proprio`: multimodal_baseline and multimodal_bidal on nicol_slide, as they are (the image and all 40 proprio
  features): the level the rungs below are measured against.

A column has a gap to close when every seed of its `proprio` cell is clearly above the task's floor and its `image`
cell's final success (the mean over seeds of each seed's mean over its last `--last-n` epochs) is more than `CLOSE`
below the `proprio` cell's; a rung closes it when Welch's 95 % interval of its per-seed finals less the `proprio`
cell's lies at or above −`CLOSE`. The table names the first rung that does, with that interval, or says that none
does, or that the gap is not measured while a rung below the first that closes it, or the `proprio` cell, is
unfinished or stale (`rungs.gap_line`). Then the linear probe (`experiments.probes.encoder`) of every finished
cell's encoder at its latest checkpoint, and of the same architecture randomly initialised: ridge regression from
φ(s), and from the vision branch's output, to the true `obj_pos` and `ee_pos` on frames of `--probe-episodes`
scripted nicol_slide episodes, held-out episodes scored (R² and RMSE in cm per axis), into OUT/probe.json; a cell
already probed at its latest checkpoint (its step and the CRC-32 of its digest, `checkpoint_digest`) is not probed
again. The probe runs in this process after training; with `--ray` this process keeps JAX on the CPU (the GPUs are
the cells'), so the probe waits for a run of the same command without `--ray` (every cell then done: only the probe
runs). `--no-probe` skips it.

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
import sys
import zlib
from typing import Sequence

import jax

import envs_mjx
from bidal_jax.config import ConfigError, option
from bidal_jax.run import checkpoint, multihost, rundir, runfiles
from experiments import cli, cluster, report
from experiments.paper import grid
from experiments.paper.grid import Arm
from experiments.paper.protocol import DEFAULT_SEED, paper_epochs
from experiments.paper.rungs import (
    ABOUT,
    DEFAULT_OUT,
    LAST_N,
    MULTIMODAL,
    NOT_RUN,
    PILOT_SEEDS,
    PROBE_FILE,
    RUNG_SEEDS,
    RUNGS,
    TASK,
    VISUAL,
    ladder_arms,
    loaded_runs,
    probe_summary,
    read_probes,
    table_text,
)
from experiments.probes import encoder

PROG = "python -m experiments.paper.ladder"
PROBE_EPISODES = 200  # scripted episodes of the probe's frames: 10,000 frames, a fifth of the episodes held out


def build_parser() -> argparse.ArgumentParser:
    parser = grid.experiment_parser(PROG, __doc__, "every run")
    parser.add_argument("--rungs", default=",".join(r.name for r in RUNGS),
                        help=f"comma list of the rungs to train (default all: {', '.join(r.name for r in RUNGS)})")
    parser.add_argument("--agents", default=",".join(dict.fromkeys(VISUAL + MULTIMODAL)),
                        help="comma list of the agents to train of the chosen rungs (default all), e.g. one column, or "
                        "one agent a process so that two processes share a GPU")
    parser.add_argument("--seeds", type=int, default=None, help="seeds of every cell, vmapped as one program (default "
                        f"each rung's: {PILOT_SEEDS} for the image rung, {RUNG_SEEDS} for the others)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED, help="first random seed of every run")
    parser.add_argument("--epochs", type=int, default=None,
                        help=f"epochs of every run (default {TASK}'s budget, {paper_epochs()[TASK]})")
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



def checkpoint_digest(run_dir: str, step: int) -> str | None:
    """The CRC-32 (hex) of the digest item of the run's checkpoint `step` (`checkpoint.digest`: a checksum of every
    state leaf, a few kilobytes): it tells a run retrained to the same step from the one probed there, which the step
    cannot, and survives copying the run folder, which a file's time would not; None where the checkpoint has none."""
    path = os.path.join(run_dir, "checkpoints", str(step), "digest", "metadata")  # the JSON item as Orbax writes it
    if not os.path.isfile(path):
        return None
    with open(path, "rb") as f:
        return f"{zlib.crc32(f.read()):08x}"


def to_probe(arms: Sequence[Arm], probes: dict) -> list[Arm]:
    """The arms whose run is at its epochs with a checkpoint there, and whose probe is missing or of another
    checkpoint: another step or another digest (`checkpoint_digest`; an entry written before probes kept it has
    none, so its cell is probed again)."""
    found = []
    for arm in arms:
        step = checkpoint.latest_step(os.path.join(arm.run_dir, "checkpoints"))
        entry = probes.get(arm.name, {})
        probed = (entry.get("step"), entry.get("digest"))
        if step is not None and step >= arm.epochs and probed != (step, checkpoint_digest(arm.run_dir, step)):
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
        step = checkpoint.latest_step(os.path.join(arm.run_dir, "checkpoints"))
        trained = encoder.load_encoder(arm.run_dir, step)
        arm_env = envs_mjx.make(arm.given["env"], render=False)
        segments = arm_env.observation_spec.segment_names
        probes[arm.name] = {
            "run_dir": arm.run_dir, "step": step, "digest": checkpoint_digest(arm.run_dir, step), "episodes": episodes,
            "frames": [int(train.sum()), int(test.sum())],
            "trained": encoder.probe(trained, frames, segments),
            "random": encoder.probe(encoder.random_encoder(trained, arm_env), frames, segments),
        }
        path = os.path.join(out, PROBE_FILE)
        with rundir.writing(path):
            runfiles.write_atomic(path, json.dumps({"cells": probes}, indent=1) + "\n")
        print(f"probe: {arm.name}: {probe_summary(probes[arm.name], 'trained', 'phi')}", flush=True)


# ----- the record (figures.json) --------------------------------------------------------------------------------


def machines(runs: dict[str, dict]) -> str:
    """The machines and physics engines the runs' config.json records, distinct, or `NOT_RUN`."""
    def named(run: dict) -> str:
        engines = run["config"].get("physics_engine") or ["physics not recorded"]
        return (f"{' then '.join(run['config'].get('hardware') or ['machine not recorded'])}, "
                f"{' then '.join(report.ENGINES.get(e, e) for e in engines)}")

    found = dict.fromkeys(named(run) for run in runs.values())
    return "; ".join(found) or NOT_RUN


def joined(previous: str | None, now: str) -> str:
    """`previous` (a record's "; "-joined values; None for none) with `now` added unless already there."""
    values = previous.split("; ") if previous else []
    return "; ".join(values + ([] if now in values else [now]))


def section(previous: dict | None, runs: dict[str, dict], command: str | None) -> dict:
    """The ladder's figures.json section: the previous record (none while its date is `NOT_RUN`) with `command` (this
    invocation's; None when it trained and probed nothing), today's date and this commit added; the machines of the
    runs (`machines`), `ABOUT`, the figure where a run has epochs, and the previous record of the runs that shared a
    GPU ("gpu_sharing", written by whoever ran them: `report.gpu_sharing`), which no run folder records."""
    previous = previous if previous and previous.get("date", NOT_RUN) != NOT_RUN else {}
    record = {key: previous.get(key) for key in ("command", "date", "commit")}
    if command is not None:
        record = {"command": joined(record["command"], command),
                  "date": joined(record["date"], datetime.date.today().isoformat()),
                  "commit": joined(record["commit"], report.checkout_commit())}
    return {"part": "Learning (paper Fig. 4)", "title": "A ladder for the pixel agents", "about": ABOUT,
            "command": record["command"] or PROG, "machine": machines(runs), "date": record["date"] or NOT_RUN,
            "commit": record["commit"] or NOT_RUN, "table": "ladder", "runs": "ladder",
            **({"figure": "curves.png"} if runs else {}),
            **({"gpu_sharing": previous["gpu_sharing"]} if previous.get("gpu_sharing") else {})}


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
