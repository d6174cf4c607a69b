"""docs/results.md and docs/performance.md, written from the figures that live beside the runs in results/.

    python -m experiments.paper.results_docs [--check]

Each folder of `FOLDERS` under results/ holds figures.json: a list of sections, each with its part of the documents
(one of `PARTS`; `PAGES` says which page holds each part), title, `about` (what it measures), the command that
measures it, the machine, the date and commit the figures were recorded at, and its table: given as {"head": [...],
"rows": [[...], ...]} (figures entered by hand, such as timings) or the name of a table computed from run files
(`TABLES`), whose "runs" field says which (paths relative to results/). Optional: a `note` (what the figures say)
and a `figure` (an image in the folder). A measurement that is superseded is replaced in its figures.json; git keeps
its history.

The command writes both pages (each a pure function of those files, `document`); `--check` writes nothing and
exits 1 when a page is not what it would write, as tests/experiments/paper/test_results_docs.py checks. Exit codes: 2
a figures.json or run file that cannot be read, 4 the write failed (one `error: ...` line each), 130 Ctrl-C.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import sys
from typing import Callable, Sequence

import numpy as np

import envs_mjx
from bidal_jax.config import AGENTS
from bidal_jax.run import rundir, runfiles
from experiments import cli, report, stats
from experiments.bench import floor_table
from experiments.paper import grid, protocol, rungs

PROG = "python -m experiments.paper.results_docs"
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PARTS = ("Performance", "Learning (paper Fig. 4)", "Noise (paper Table II)", "Transfer (paper Fig. 6)",
         "Reliability")
# each page, its title and its parts: the learning results apart from the speed figures
PAGES = {os.path.join("docs", "results.md"): ("Results", PARTS[1:]),
         os.path.join("docs", "performance.md"): ("Performance", PARTS[:1])}
# the folders of results/ in the order of their sections; each is linked from its sections
FOLDERS = ("scaling", "parity", "floors", "curves", "pilots", "lambda", "lift", "strides", "vision_probe", "camera",
           "ladder", "noise", "noise_probe", "transfer", "reliability")
FIELDS = ("part", "title", "about", "command", "machine", "date", "commit", "table")
LAST_N = 10  # the final success's window: each seed's mean over its last 10 epochs
HEAD = f"""<!-- written by `{PROG}` from results/*/figures.json and the runs beside them: edit those -->
# {{title}}

Written by `{PROG}` from each experiment's figures.json and run folders under results/. Every
section names what it measures, the command, the machine, and the date and commit of its figures. Success is the
evaluation success rate (deterministic policy, success at the episode's last step), the mean over seeds; "final" is
the mean ± std over seeds of each seed's mean over its last {LAST_N} epochs; AUC is the mean of the seed-mean success
over the epochs run. The paper's claims judged on these runs are in [results/claims.md](../results/claims.md), how
far each verdict bears on the paper in [reproduction.md](reproduction.md); the learning results are in
[results.md](results.md), the speed figures in [performance.md](performance.md)."""


def sweep_curve(path: str, label: str) -> report.Curve:
    """A sweep's curve (one variant's JSON lines): each epoch's per-seed eval success."""
    rows = grid.read_lines(path)
    column = [np.array([row[key] for row in rows], float) for key in ("epoch", "env_steps_per_seed",
                                                                       "process_seconds")]
    return report.Curve("", label, path, *column, np.array([row["eval_success_seeds"] for row in rows], float))


def curve_of(path: str, label: str) -> report.Curve:
    """The curve of a run folder or of a sweep's JSON lines (a path ending .jsonl)."""
    if path.endswith(".jsonl"):
        return sweep_curve(path, label)
    return report.curves([report.load_run(path)], labels={path: label})[0]


def first_epoch(epochs: np.ndarray, success: np.ndarray, threshold: float = 0.9) -> str:
    """The first of `epochs` whose seed mean of `success` [E, S] is at least `threshold`; "—" if none is."""
    reached = np.flatnonzero(success.mean(axis=1) >= threshold)
    return str(int(epochs[reached[0]])) if reached.size else "—"


def epochs_table(root: str, runs: str) -> str:
    """Per sweep file TASK-AGENT[-N-seeds].jsonl: its physics, seeds, the mean step of `process_seconds` per epoch,
    and compile: the first epoch's `variant_seconds` less one epoch (`grid.sweep_seconds`: what the grid's estimates
    read)."""
    rows = []
    for path in glob.glob(os.path.join(root, runs)):
        task, agent = os.path.basename(path).removesuffix(".jsonl").split("-")[:2]
        lines = grid.read_lines(path)
        epoch, compile_s = grid.sweep_seconds(lines)
        rows.append((envs_mjx.names().index(task), list(AGENTS).index(agent), [
            task, agent, str(len(lines[0]["eval_success_seeds"])), report.ENGINES[lines[0]["engine"]], f"{epoch:.2f}",
            f"{compile_s:.1f}"]))
    head = ["task", "agent", "seeds", "physics", "epoch (s)", "compile (s)"]
    return report.markdown_table(head, [cells for *_, cells in sorted(rows)])


def curves_table(root: str, runs: str) -> str:
    """The learning-curve grid OUT/<task>/<agent>: an agent a row, a task a column headed by its budget
    (`protocol.paper_epochs`), "final / AUC"; "—" for a cell without its run folder (an agent not run on that task yet);
    a cell whose run is not today's (`grid.stale_runs` against the cell the grid trains there by default,
    `grid.curve_arms`, and its task's physics today) marked with `grid.STALE` (its epochs are its own); the last row
    the tasks' floors over all goals (root/floors, `report.load_floors`). Each run folder is read once."""
    out = os.path.join(root, runs)
    budgets = protocol.paper_epochs()
    tasks = [t for t in budgets if os.path.isdir(os.path.join(out, t))]
    arms = [arm for arm in grid.curve_arms(tasks, AGENTS, protocol.DEFAULT_SEEDS, protocol.DEFAULT_SEED, None, {}, out)
            if os.path.isdir(arm.run_dir)]
    found = {arm.name: report.load_run(arm.run_dir) for arm in arms}
    stale = set(grid.stale_runs(arms, found, grid.physics_today(tasks)))
    names = {(arm.given["env"], arm.given["agent"]): arm.name for arm in arms}
    agents = [a for a in AGENTS if any((t, a) in names for t in tasks)]
    head = ["agent", *(f"{t} ({budgets[t]} epochs)" for t in tasks)]

    def cell(task: str, agent: str) -> str:
        name = names.get((task, agent))
        if name is None:
            return "—"
        curve = report.curves([found[name]], labels={found[name]["dir"]: agent})[0]
        mark = grid.STALE if name in stale else ""
        return f"{report.final_cell(curve, LAST_N)} / {report.normalized_auc(curve):.3f}{mark}"

    floors = report.load_floors(os.path.join(root, "floors"))
    rows = [[a, *(cell(t, a) for t in tasks)] for a in agents]
    rows.append(["floor: a policy that does nothing", *(report.floor_value(floors, t) for t in tasks)])
    return report.markdown_table(head, rows)


def floors_table(root: str, runs: str) -> str:
    """Each task's floor (root/runs/figures.json, `report.load_floors`): a row a task, a column per goal subset,
    each estimate ± its 95 % Monte Carlo half-width; "—" for a subset the task does not have."""
    floors = report.load_floors(os.path.join(root, runs))
    subsets = list(dict.fromkeys(name for found in floors.values() for name in sorted(found, key=lambda n: n != "all")))
    rows = [[task, *(f"{f.value:.4f} ± {f.half_width:.4f}" if (f := found.get(name)) else "—" for name in subsets)]
            for task, found in floors.items()]
    return report.markdown_table(["task", *(f"{name} goals" for name in subsets)], rows)


def pilots_table(root: str, runs: Sequence[Sequence[str]]) -> str:
    """Per [label, path] (a run folder or a sweep): seeds, epochs, the first epoch of seed mean ≥ 0.9, final."""
    rows = []
    for label, path in runs:
        curve = curve_of(os.path.join(root, path), label)
        rows.append([label, str(curve.n_seeds), str(len(curve.epoch)), first_epoch(curve.epoch, curve.success),
                     report.final_cell(curve, LAST_N)])
    return report.markdown_table(["task, agent", "seeds", "epochs", "first epoch ≥ 0.9", "final"], rows)


def lambda_table(root: str, runs: str) -> str:
    """The table of the λ sweep's table.md (`experiments.paper.lambda_sweep --report`) and its verdict line."""
    with open(os.path.join(root, runs), encoding="utf-8") as f:
        lines = f.read().splitlines()
    verdict = [line for line in lines if line.startswith("Largest")]
    return "\n\n".join(["\n".join(line for line in lines if line.startswith("|")), *verdict])


def last_mean(run_dir: str, column: str) -> str:
    """The mean of metrics.csv's `column` over the last `LAST_N` rows; "not recorded" where the run predates it."""
    metrics = os.path.join(run_dir, "metrics.csv")
    header, rows, _ = runfiles.read_csv(metrics)
    if column not in header:
        return "not recorded"
    return f"{np.mean([runfiles.number(metrics, row, column) for row in rows[-LAST_N:]]):.3f}"


def lift_table(root: str, runs: Sequence[Sequence[str]]) -> str:
    """Per [protocol, path] of a nicol_lift run: air-goal success per seed and table-goal success (each over the
    last epochs), the seeds that lift (`protocol.seeds_that_lift`), the first epoch of seed-mean air success ≥ 0.9."""
    rows = []
    for label, path in runs:
        run = report.load_run(os.path.join(root, path))
        air = run["success_air"]
        final = air[-LAST_N:].mean(axis=0)
        rows.append([label, run["agent"], str(run["seeds"]), str(len(run["epoch"])),
                     ", ".join(f"{v:.3f}" for v in final), last_mean(run["dir"], "eval_success_table"),
                     f"{protocol.seeds_that_lift(final)} of {run['seeds']}", first_epoch(run["epoch"], air)])
    head = ["protocol", "agent", "seeds", "epochs", f"air goals, last {LAST_N} epochs, per seed",
            "table goals", "seeds that lift", "first epoch, air ≥ 0.9"]
    return report.markdown_table(head, rows)


def common_aucs(curves: Sequence[tuple[str, report.Curve]]) -> list[tuple[int, np.ndarray]]:
    """Per (group, curve): the epochs every curve of its group reached, and each seed's AUC over them."""
    common = {group: min(len(c.epoch) for g, c in curves if g == group) for group, _ in curves}
    return [(common[group], c.success[:common[group]].mean(axis=0)) for group, c in curves]


def parity_table(root: str, runs: Sequence[Sequence[str]]) -> str:
    """Per [task and agent, convs, sweep path]: each seed's AUC over the epochs every sweep of its task reached."""
    curves = [(task, sweep_curve(os.path.join(root, path), convs)) for task, convs, path in runs]
    rows = [[task, convs, str(n), ", ".join(f"{v:.3f}" for v in auc), f"{auc.mean():.3f}"]
            for (task, convs, _), (n, auc) in zip(runs, common_aucs(curves))]
    return report.markdown_table(["task, agent", "convs", "epochs", "AUC per seed", "mean"], rows)


def lever_table(root: str, runs: Sequence[Sequence[str]]) -> str:
    """Per [task and agent, lever, path before, path after] (run folders or sweeps): each seed's AUC over the epochs
    both reached, before and after, and the difference of the means with Welch's 95 % interval; a lever keeps parity
    where the interval holds 0 or lies above it (its upper end is not below 0)."""
    rows = []
    for task, lever, before, after in runs:
        a, b = curve_of(os.path.join(root, before), "before"), curve_of(os.path.join(root, after), "after")
        n = min(len(a.epoch), len(b.epoch))
        auc_a, auc_b = a.success[:n].mean(axis=0), b.success[:n].mean(axis=0)
        diff, low, high = stats.welch_interval(auc_b, auc_a)
        rows.append([task, lever, str(n), ", ".join(f"{v:.3f}" for v in auc_a), ", ".join(f"{v:.3f}" for v in auc_b),
                     f"{diff:+.3f} {stats.interval_text(low, high)}", "yes" if high >= 0 else "no"])
    head = ["task, agent", "change", "epochs", "AUC per seed before", "AUC per seed after",
            "difference [95 % interval]", "parity"]
    return report.markdown_table(head, rows)


def strides_table(root: str, runs: Sequence[Sequence[str]]) -> str:
    """Per [task and agent, strides, sweep path], the first row of each task and agent its reference: each seed's AUC
    over the epochs all its rows reached (`common_aucs`), their mean, the difference from the reference's with
    Welch's 95 % interval, the final success, and the epoch's wall time (`grid.sweep_seconds`, compilation
    excluded)."""
    curves = [(name, sweep_curve(os.path.join(root, path), strides)) for name, strides, path in runs]
    reference: dict[str, np.ndarray] = {}
    rows = []
    for (name, strides, path), (_, curve), (n, auc) in zip(runs, curves, common_aucs(curves)):
        if name in reference:
            diff, low, high = stats.welch_interval(auc, reference[name])
            versus = f"{diff:+.3f} {stats.interval_text(low, high)}"
        else:
            reference[name], versus = auc, "reference"
        epoch_s, _ = grid.sweep_seconds(grid.read_lines(os.path.join(root, path)))
        rows.append([name, strides, str(n), ", ".join(f"{v:.3f}" for v in auc), f"{auc.mean():.3f}", versus,
                     report.final_cell(curve, LAST_N), f"{epoch_s:.1f}"])
    head = ["task, agent", "strides", "epochs", "AUC per seed", "AUC", "difference [95 % interval]",
            f"final (last {LAST_N})", "epoch (s)"]
    return report.markdown_table(head, rows)


def noise_table(root: str, runs: str) -> str:
    """Table II: per κ, each agent's final success over the paper's last N epochs beside the paper's."""
    found, _ = protocol.load_noise_curves(os.path.join(root, runs))
    agents = [a for a in protocol.NOISE_AGENTS if any(agent == a for _, agent in found)]
    rows = []
    for k in protocol.KAPPAS:
        cells = [f"{k:.0%}", str(protocol.LAST_N[k])]
        for a in agents:
            mean, std, _ = report.final_success(found[k, a], protocol.LAST_N[k])
            cells += [f"{mean:.3f} ± {std:.3f}", "{:.3f} ± {:.3f}".format(*protocol.PAPER[k][a])]
        rows.append(cells)
    floor = report.floor_text(report.load_floors(os.path.join(root, "floors")), protocol.NOISE_ENV)
    head = [f"κ ({protocol.NOISE_ENV}'s {floor})", "last N epochs"]
    return report.markdown_table([*head, *(f"{a}{whose}" for a in agents for whose in ("", ", paper"))], rows)


def transfer_table(root: str, runs: str) -> str:
    """The transfer and scratch arms: final, AUC, env steps to each threshold; then transfer − scratch in AUC."""
    arms = [curve_of(os.path.join(root, runs, arm), arm) for arm in ("transfer", "scratch")]
    head = ["arm", "seeds", "epochs", "final", "AUC", *(f"env steps per seed to {t:g}" for t in protocol.THRESHOLDS)]
    rows = []
    for c in arms:
        hits = [report.time_to_threshold(c, t) for t in protocol.THRESHOLDS]
        rows.append([c.label, str(c.n_seeds), str(len(c.epoch)), report.final_cell(c, LAST_N),
                     f"{report.normalized_auc(c):.3f}",
                     *("not reached" if h is None else f"{h.env_steps:,.0f} (epoch {h.epoch})" for h in hits)])
    auc = [c.success.mean(axis=0) for c in arms]
    diff, low, high = stats.welch_interval(*auc)
    rows.append(["transfer − scratch, per seed: Welch's 95 % t interval", "", "", "",
                 f"{diff:+.3f} {stats.interval_text(low, high)}", *([""] * len(protocol.THRESHOLDS))])
    return report.markdown_table(head, rows)


def resumed_table(root: str, runs: str) -> str:
    """Every run folder under root/runs that resumed with an empty replay buffer or lacks rows in metrics.csv."""
    rows = []
    for config in sorted(glob.glob(os.path.join(root, runs, "**", "config.json"), recursive=True)):
        run = report.load_run(os.path.dirname(config))
        fresh, absent = run["config"].get("fresh_buffer_epochs") or [], report.absent_epochs(run["epoch"])
        if fresh or absent:
            rows.append([os.path.relpath(run["dir"], root), ", ".join(map(str, fresh)) or "—",
                         report.epoch_spans(absent) or "—"])
    return report.markdown_table(["run", "resumed with an empty replay buffer after epochs",
                                  "epochs without a row in metrics.csv"], rows)


def ladder_table(root: str, runs: str) -> str:
    """The pixel agents' ladder (`experiments.paper.ladder`) in root/runs: its rungs' success, the rung that closes
    the gap, the probe of the visual agents' φ; "not run" where its runs or its probe are not there yet."""
    return rungs.docs_table(os.path.join(root, runs))


def roofline_table(root: str, runs: Sequence[str]) -> str:
    """[the counted floors (`experiments.bench.roofline --out`), the measured rows (`experiments.bench.updates
    --json`), the measured row's variant]: each part of an update against its own floor (`floor_table.parts_table`)."""
    counted_path, measured_path, variant = runs
    with open(os.path.join(root, counted_path), encoding="utf-8") as f:
        counted = json.load(f)
    with open(os.path.join(root, measured_path), encoding="utf-8") as f:
        measured = [row for row in json.load(f) if row["variant"] == variant]
    if not measured:
        raise ValueError(f"{measured_path}: no row of variant {variant!r}")
    return report.markdown_table(*floor_table.parts_table(counted, measured[0]))


TABLES: dict[str, Callable[[str, object], str]] = {
    "epochs": epochs_table, "floors": floors_table, "curves": curves_table, "pilots": pilots_table,
    "lambda": lambda_table, "lift": lift_table, "parity": parity_table, "levers": lever_table, "noise": noise_table,
    "transfer": transfer_table, "resumed": resumed_table, "ladder": ladder_table, "strides": strides_table,
    "roofline": roofline_table,
}


def load_sections(root: str, folders: Sequence[str]) -> list[dict]:
    """The sections of each folder's figures.json, each with its "folder"; ValueError naming a bad one."""
    sections = []
    for folder in folders:
        path = os.path.join(root, folder, "figures.json")
        with open(path, encoding="utf-8") as f:
            found = json.load(f)
        for i, section in enumerate(found):
            missing = [field for field in FIELDS if field not in section]
            if missing or section["part"] not in PARTS:
                raise ValueError(f"{path}: section {i + 1} lacks {', '.join(missing)}" if missing
                                 else f"{path}: section {i + 1}: part {section['part']!r} is none of {PARTS}")
            sections.append({**section, "folder": folder})
    return sections


def table_text(section: dict, root: str) -> str:
    """A section's table: given, or computed by its `TABLES` function from its runs."""
    table = section["table"]
    if isinstance(table, dict):
        return report.markdown_table(table["head"], table["rows"])
    if table not in TABLES:
        raise ValueError(f"{section['folder']}/figures.json: table {table!r} is none of {', '.join(TABLES)}")
    return TABLES[table](root, section["runs"])


def section_text(section: dict, root: str) -> str:
    """A section: its title, what it measures, then its command, machine and record beside its table, its note
    and its figure."""
    folder = f"../results/{section['folder']}/"
    record = (f"Command: `{section['command']}`. Machine: {section['machine']}. Recorded {section['date']} at "
              f"commit {section['commit']}; data: [results/{section['folder']}/]({folder}).")
    parts = [f"### {section['title']}", section["about"], record, table_text(section, root)]
    parts += [section["note"]] if section.get("note") else []
    parts += [f"![{section['title']}]({folder}{section['figure']})"] if section.get("figure") else []
    return "\n\n".join(parts)


def document(root: str, folders: Sequence[str], page: str = os.path.join("docs", "results.md")) -> str:
    """A page's text (a key of `PAGES`) from the figures of `folders` and the runs under `root` (a results/
    folder)."""
    sections = load_sections(root, folders)
    title, page_parts = PAGES[page]
    parts = [HEAD.format(title=title)]
    for part in page_parts:
        parts += [f"## {part}"] + [section_text(s, root) for s in sections if s["part"] == part]
    return "\n\n".join(parts) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=f"Write {' and '.join(PAGES)} from "
                                     "results/*/figures.json.")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when a page is not what the "
                        "command writes")
    args = parser.parse_args(argv)
    try:
        texts = {page: document(os.path.join(REPO, "results"), FOLDERS, page) for page in PAGES}
        for page, text in texts.items():
            path = os.path.join(REPO, page)
            if args.check:
                with open(path, encoding="utf-8") as f:
                    if f.read() != text:
                        print(f"error: {page} is not what `{PROG}` writes: run it", file=sys.stderr)
                        return 1
                continue
            with rundir.writing(path):
                runfiles.write_atomic(path, text)
    except (OSError, ValueError, KeyError, rundir.DiskError) as err:  # report.RunError is a ValueError
        return cli.exit_code(err)
    return 0


if __name__ == "__main__":
    sys.exit(cli.command(main))
