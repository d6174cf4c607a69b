"""The time-to-threshold benchmark (experiments/bench/success.py) without training: its figures
from hand-written run directories and stderr (`fake_run` of conftest.py), the table, refusals,
the order of the runs and the ref's worktree with a fake `launch`, and the launcher on a real
command that stops before compiling."""

import csv
import json
import os
import subprocess
from pathlib import Path

import pytest

from experiments.bench import success as bs

LOG = ("compiling the training program (planar_reach, proprio_baseline, 3 seed(s) on 1 device(s)) ...\n"
       "compiled in 12.5 s\n")
ROWS = [(0.0, 0.25, 0.5), (0.5, 0.75, 1.0), (1.0, 1.0, 0.875)]  # each epoch's per-seed success: means 0.25, 0.75, 0.96


def _run_dir(path, fake_run, rows=ROWS, wall=None):
    """A run directory as experiments.run writes it: 100 env steps per seed and (unless `wall`
    gives the times) 10 s per epoch, 10 cycles of 40 updates per epoch."""
    fake_run(str(path), "planar_reach", rows, None, agent="proprio_baseline")
    config = json.loads((path / "config.json").read_text())
    config["train"] = {"cycles_per_epoch": 10, "updates_per_cycle": 40}
    (path / "config.json").write_text(json.dumps(config))
    if wall:
        with open(path / "metrics.csv", newline="") as f:
            rows = list(csv.DictReader(f))
        with open(path / "metrics.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, list(rows[0]))
            writer.writeheader()
            writer.writerows({**row, "wall_time": w} for row, w in zip(rows, wall))
    return str(path)


def test_the_logged_compile_is_outside_the_wall_time():
    assert bs.compile_seconds(LOG, [10.0, 20.0]) == (12.5, 0.0, "log")


def test_without_the_line_the_compile_is_the_first_epochs_excess():
    # durations 30, 10, 12, 9: the first less the median of the others (10)
    assert bs.compile_seconds("", [30.0, 40.0, 52.0, 61.0]) == (20.0, 20.0, "first epoch")
    assert bs.compile_seconds("", [30.0]) == (None, None, "first epoch")


def test_figures_of_a_run_that_reached_the_threshold(tmp_path, fake_run):
    figures = bs.run_figures(_run_dir(tmp_path / "run", fake_run), LOG, 51.5, 0.7)
    assert figures == {"compile_s": 12.5, "compile_from": "log", "epochs_run": 3, "reached": True, "training_s": 20.0,
                       "total_s": 51.5, "epochs": 2, "env_steps_per_seed": 200.0, "updates": 800}


def test_a_run_that_never_reached_it_has_no_times(tmp_path, fake_run):
    figures = bs.run_figures(_run_dir(tmp_path / "run", fake_run), LOG, 51.5, 0.99)
    assert figures["reached"] is False and figures["epochs_run"] == 3 and figures["compile_s"] == 12.5
    assert [figures[k] for k in ("training_s", "total_s", "epochs", "env_steps_per_seed", "updates")] == [None] * 5


def test_an_older_commit_compiles_in_the_first_epoch_which_training_leaves_out(tmp_path, fake_run):
    run_dir = _run_dir(tmp_path / "run", fake_run, wall=[40.0, 50.0, 60.0])
    figures = bs.run_figures(run_dir, "no compile line here\n", 70.0, 0.7)
    assert (figures["compile_s"], figures["compile_from"], figures["training_s"]) == (30.0, "first epoch", 20.0)
    one_epoch = _run_dir(tmp_path / "one", fake_run, rows=ROWS[1:2], wall=[40.0])
    assert bs.run_figures(one_epoch, "", 70.0, 0.7)["training_s"] is None  # reached, but the compile is unknown


def _figures(cache, compile_s, training_s=None, epochs=None, compile_from="log"):
    """One run's figures; it reached the threshold if it has a training time (and then 9 s more in all)."""
    return {"cache": cache, "compile_s": compile_s, "compile_from": compile_from, "training_s": training_s,
            "total_s": training_s and training_s + 9, "epochs": epochs, "env_steps_per_seed": epochs and 100.0 * epochs,
            "updates": epochs and 400 * epochs, "reached": training_s is not None, "epochs_run": epochs or 40}


def test_summary_medians_by_cache():
    runs = [_figures("cold", 30.0, 20.0, 2), _figures("warm", 10.0, 24.0, 2), _figures("cold", 34.0, 22.0, 2),
            _figures("warm", 12.0, None)]
    summary = bs.summarize(runs)
    assert summary == {"compile_cold_s": 32.0, "compile_warm_s": 11.0, "training_s": 22.0, "total_cold_s": 30.0,
                       "total_warm_s": 33.0, "epochs": 2, "env_steps_per_seed": 200.0, "updates": 800,
                       "reached": 3, "runs": 4, "epochs_run": 40, "compile_from": "log"}


def test_table_with_a_ref_has_the_ratio_this_over_ref():
    this = bs.summarize([_figures("cold", 30.0, 20.0, 2), _figures("warm", 10.0, 20.0, 2)])
    ref = bs.summarize([_figures("cold", 60.0, 40.0, 4, compile_from="first epoch"),
                        _figures("warm", None, compile_from="first epoch")])
    lines = bs.table({"planar": {"this": this, "ref": ref}}, {"this": "aaaaaaa", "ref": "bbbbbbb"}).splitlines()
    assert lines[:2] == ["| case | quantity | this (aaaaaaa) | ref (bbbbbbb) | this ÷ ref |",
                         "| --- | --- | --- | --- | --- |"]
    assert lines[2:] == [
        "| planar | compile, cold cache | 30.0 s | 60.0 s | 0.50 |",
        "| planar | compile, warm cache | 10.0 s | — | — |",
        "| planar | training to the threshold | 20.0 s | 40.0 s | 0.50 |",
        "| planar | total to the threshold, cold cache | 29.0 s | 49.0 s | 0.59 |",
        "| planar | total to the threshold, warm cache | 29.0 s | — | — |",
        "| planar | epochs | 2 | 4 | 0.50 |",
        "| planar | env steps per seed | 200 | 400 | 0.50 |",
        "| planar | gradient updates per seed | 800 | 1,600 | 0.50 |",
        "| planar | threshold reached | yes | 1 of 2 runs |  |",
        "| planar | compile from | log | first epoch |  |",
    ]


def test_table_of_this_commit_alone():
    never = bs.summarize([_figures("cold", 30.0), _figures("warm", 10.0)])
    lines = bs.table({"main": {"this": never}}, {"this": "aaaaaaa"}).splitlines()
    assert lines[0] == "| case | quantity | this (aaaaaaa) |"
    assert lines[4] == "| main | training to the threshold | — |"
    assert lines[-2:] == ["| main | threshold reached | no (40 epochs) |", "| main | compile from | log |"]


def _worktrees():
    return subprocess.run(["git", "-C", bs.ROOT, "worktree", "list"], capture_output=True, text=True, check=True).stdout


@pytest.mark.parametrize("argv, message", [
    (["--cases", "planar,nope"], "error: --cases: unknown case 'nope'; allowed: planar, main (comma-separated)"),
    (["--target", "0"], "error: --target 0.0: must be in (0, 1]"),
    (["--target", "1.5"], "error: --target 1.5: must be in (0, 1]"),
    (["--repeats", "0"], "error: --repeats 0: must be at least 1"),
    (["--ref", "no-such-ref"], f"error: --ref no-such-ref: not a commit of the git repository at {bs.ROOT}"),
])
def test_bad_input_is_one_line_exit_2_and_runs_nothing(argv, message, monkeypatch, capsys):
    monkeypatch.setattr(bs, "launch", lambda *a: pytest.fail("a run was started"))
    before = _worktrees()
    assert bs.main(argv) == 2
    assert capsys.readouterr().err.splitlines() == [message]
    assert _worktrees() == before


@pytest.fixture
def fake_launch(monkeypatch, fake_run):
    """`launch` writing a run that reaches 0.7 at epoch 2 in 20 s (after a 12.5 s compile), 50 s in
    all; records (checkout, the commit checked out there, args, cache) of each call."""
    calls = []

    def launch(tree, args, cache):
        head = subprocess.run(["git", "-C", tree, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
        calls.append((tree, head, args, cache))
        run_dir = args[args.index("--run-dir") + 1]
        _run_dir(Path(run_dir), fake_run)
        return LOG, 50.0

    monkeypatch.setattr(bs, "launch", launch)
    return calls


def test_with_a_ref_each_case_runs_there_then_here_and_the_worktree_goes(fake_launch, tmp_path, capsys):
    head = subprocess.run(["git", "-C", bs.ROOT, "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    out = tmp_path / "out.json"
    before = _worktrees()
    argv = ["--ref", "HEAD", "--cases", "main,planar", "--target", "0.7", "--epochs", "3", "--out", str(out)]
    assert bs.main(argv) == 0
    ref_tree = fake_launch[0][0]
    assert ref_tree != bs.ROOT and not os.path.exists(ref_tree) and _worktrees() == before
    # per case: ref cold, ref warm, this cold, this warm; one fresh cache per commit and case
    order = [(tree, commit) for tree, commit, _, _ in fake_launch]
    assert order == ([(ref_tree, head)] * 2 + [(bs.ROOT, head)] * 2) * 2
    caches = [cache for *_, cache in fake_launch]
    assert caches[0::2] == caches[1::2] and len(set(caches)) == 4
    args = fake_launch[0][2]
    assert args == ["--env", "ur5_reach", "--epochs", "3", "--run-dir", args[5], "--quiet", "--target-success", "0.7"]
    assert fake_launch[4][2][:6] == ["--env", "planar_reach", "--agent", "proprio_baseline", "--seeds", "3"]
    assert len({a[a.index("--run-dir") + 1] for _, _, a, _ in fake_launch}) == 8  # a new run directory each

    printed = capsys.readouterr().out
    assert f"ref: {bs.resolve_commit(bs.ROOT, head)}\n" in printed
    assert "cold cache: compile 12.5 s; eval success ≥ 0.7 at epoch 2 (training 20.0 s), total 50.0 s" in printed
    assert "| main | training to the threshold | 20.0 s | 20.0 s | 1.00 |" in printed
    saved = json.loads(out.read_text())
    assert list(saved["cases"]) == ["main", "planar"] and list(saved["cases"]["main"]) == ["this", "ref"]
    assert saved["cases"]["planar"]["ref"]["summary"]["total_cold_s"] == 50.0
    assert [r["cache"] for r in saved["cases"]["planar"]["this"]["runs"]] == ["cold", "warm"]


def test_the_worktree_is_removed_on_ctrl_c(monkeypatch, capsys):
    trees = []

    def interrupted(tree, args, cache):
        trees.append(tree)
        raise KeyboardInterrupt

    monkeypatch.setattr(bs, "launch", interrupted)
    before = _worktrees()
    assert bs.main(["--ref", "HEAD", "--cases", "planar"]) == 130
    assert trees and not os.path.exists(trees[0]) and _worktrees() == before
    assert capsys.readouterr().err.splitlines() == ["interrupted"]


def test_the_launcher_runs_the_checkouts_own_code_assets_included(tmp_path):
    """A worktree of HEAD runs a command refused after it built the env (its MJCF model): the
    run's own error, not the launcher's about a module imported from elsewhere."""
    huge = ["--env", "planar_reach", "--agent", "proprio_baseline", "--buffer-episodes", "1600000000"]
    with bs.worktree(bs.ROOT, "HEAD") as tree, pytest.raises(RuntimeError) as err:
        bs.launch(tree, [*huge, "--run-dir", str(tmp_path / "run"), "--quiet"], str(tmp_path / "cache"))
    assert f"in {tree} exited with 2: error: --seeds 1: the training state needs" in str(err.value)
    assert not (tmp_path / "run").exists()
