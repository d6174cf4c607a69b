"""The transfer experiment (experiments/paper/transfer_learning.py) on hand-written run directories:
it skips finished runs, resumes interrupted ones, trains only the arms asked for and tabulates both
arms; its options are checked before anything runs."""

import csv
import os
import shutil

import pytest

from experiments.paper import grid
from experiments.paper import transfer_learning as experiment
from tests.conftest import TODAY, write_fake_run

# per arm: per-epoch per-seed eval success (2 seeds); epochs of 100 env steps per seed, 10 s each
FAKE = {
    "source": [(0.1, 0.3), (0.5, 0.7)],
    "transfer": [(0.2, 0.4), (0.4, 0.6), (0.6, 0.8)],
    "scratch": [(0.0, 0.2), (0.1, 0.1), (0.3, 0.5)],
}
EXPERIMENT = ["--seeds", "2", "--epochs", "3", "--source-epochs", "2", "--last-n", "2", "--quiet"]


@pytest.fixture
def fake_run():
    """`write_fake_run` of a run made today for its arm of `EXPERIMENT`: on today's physics (`no_nicol`'s), with the
    arm's config (the source 2 epochs, the reduced-lift arms 3)."""
    def write(run_dir, env, rows, checkpoint_epoch, **kwargs):
        epochs = 2 if env == "nicol_slide" else 3
        write_fake_run(run_dir, env, rows, checkpoint_epoch, physics=[TODAY], given={"epochs": epochs}, **kwargs)
    return write


def test_finished_runs_are_skipped_and_the_table_and_plot_written(tmp_path, no_nicol, fake_run, capsys):
    out = tmp_path / "out"
    for name, rows in FAKE.items():
        fake_run(str(out / name), "nicol_slide" if name == "source" else "nicol_lift_reduced", rows, len(rows),
                 compile_seconds=50.0 if name == "transfer" else None)  # scratch: recorded before that column
    assert experiment.main([*EXPERIMENT, "--out", str(out)]) == 0
    assert no_nicol == []
    printed = capsys.readouterr().out
    assert (
        "source: nicol_slide multimodal_bidal, 2 seed(s), exploration starts 0; 2 epochs × 128,000 = 256,000" in printed
    )
    assert (
        "transfer: nicol_lift_reduced multimodal_bidal, 2 seed(s), exploration starts 0.5, "
        f"parameters from {out}/source" in printed
    )
    assert "3 epochs × 204,800 = 614,400 env steps per seed" in printed and "[done]" in printed
    table = (out / "table.md").read_text()
    # transfer: means 0.3, 0.5, 0.7 -> 0.3 at epoch 1 (100 steps, 10 s; its 50 s of compiling not counted), 0.5 at
    # epoch 2; AUC 0.5; last 2: seeds 0.5, 0.7
    assert "| transfer | 2 | 3 | 300 | 100 (epoch 1) | 10 s | 200 (epoch 2) | 20 s | 0.500 | 0.600 ± 0.100 |" in table
    assert "Times are each run's seconds of training (`wall_time`), compilation not counted" in table
    # scratch: means 0.1, 0.1, 0.4 -> 0.3 at epoch 3, 0.5 never; AUC 0.2; last 2: seeds 0.2, 0.3
    assert (
        "| scratch | 2 | 3 | 300 | 300 (epoch 3) | 30 s | not reached | not reached | 0.200 | 0.250 ± 0.050 |" in table
    )
    assert "Source: nicol_slide multimodal_bidal" in table and "2 epochs, 200 env steps per seed, 20 s" in table
    assert "Stale" not in table
    assert "| AUC | 0.500 | 0.200 | 0.300 |" in table  # transfer − scratch (tests/experiments/test_stats.py)
    assert (
        f"Regenerate from the run folders: `python -m experiments.paper.transfer_learning --arms none --out {out} "
        "--seeds 2 --last-n 2`" in table
    )
    with open(out / "success.png", "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    with open(out / "success.csv", newline="") as f:
        assert {r["label"] for r in csv.DictReader(f)} == {"transfer", "scratch"}


def test_interrupted_runs_resume_and_runs_without_a_checkpoint_start_again(tmp_path, no_nicol, fake_run, capsys):
    out = tmp_path / "out"
    fake_run(str(out / "source"), "nicol_slide", FAKE["source"], 2)  # done
    fake_run(str(out / "transfer"), "nicol_lift_reduced", FAKE["transfer"][:1], 1)  # interrupted at epoch 1 of 3
    os.makedirs(out / "scratch")
    (out / "scratch" / "metrics.csv").write_text("epoch\n")  # stopped before its first checkpoint
    assert experiment.main([*EXPERIMENT, "--out", str(out)]) == 0
    assert no_nicol == [
        ("prepare", str(out / "transfer"), True, False),
        ("train", str(out / "transfer"), True, True),
        ("prepare", str(out / "scratch"), False, True),
        ("train", str(out / "scratch"), False, False),
    ]
    assert "[resume, checkpoint at epoch 1]" in capsys.readouterr().out
    assert "| transfer | 2 | 1 | 100 |" in (out / "table.md").read_text()  # from whatever is there


def test_a_short_arm_is_named_and_the_intervals_are_marked_as_not_the_experiment(tmp_path, no_nicol, fake_run):
    out = tmp_path / "out"
    fake_run(str(out / "source"), "nicol_slide", FAKE["source"], 2)
    fake_run(str(out / "transfer"), "nicol_lift_reduced", FAKE["transfer"], 3)
    fake_run(str(out / "scratch"), "nicol_lift_reduced", FAKE["scratch"][:2], 2)  # 2 of its 3 epochs
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "none"]) == 0
    table = (out / "table.md").read_text()
    assert "Missing: none. Unfinished: scratch (epoch 2 of 3)." in table
    assert "**Not the experiment yet**: the arms have run 3 and 2 of their 3 epochs (transfer, scratch)" in table
    shutil.rmtree(out / "scratch")
    fake_run(str(out / "scratch"), "nicol_lift_reduced", FAKE["scratch"], 3)
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "none"]) == 0
    table = (out / "table.md").read_text()
    assert "No run is missing or unfinished." in table and "Not the experiment yet" not in table


def test_dry_run_prints_each_runs_state_and_trains_and_writes_nothing(tmp_path, no_nicol, fake_run, capsys):
    out = tmp_path / "out"
    fake_run(str(out / "source"), "nicol_slide", FAKE["source"], 2)  # done
    fake_run(str(out / "transfer"), "nicol_lift_reduced", FAKE["transfer"][:1], 1)  # interrupted at epoch 1 of 3
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert no_nicol == [] and sorted(p.relative_to(out) for p in out.rglob("*")) == before
    assert f"{out}/source [done]" in printed and f"{out}/transfer [resume, checkpoint at epoch 1]" in printed
    assert f"{out}/scratch [new]; estimated " in printed and printed.endswith("dry run: nothing trained or written\n")
    assert f"{out}/source [done]; estimated 0 s" in printed and "estimated time: " in printed


def test_arms_trains_only_the_named_runs_and_tabulates_what_exists(tmp_path, no_nicol, fake_run):
    out = tmp_path / "out"
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "scratch"]) == 0
    assert no_nicol == [("prepare", str(out / "scratch"), False, True), ("train", str(out / "scratch"), False, False)]
    shutil.rmtree(out / "scratch" / "checkpoints", ignore_errors=True)
    fake_run(str(out / "transfer"), "nicol_lift_reduced", FAKE["transfer"], 1)
    shutil.rmtree(out / "transfer" / "checkpoints")  # results only: checkpoints are not needed
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "none"]) == 0
    assert len(no_nicol) == 2 and "| transfer | 2 | 3 | 300 |" in (out / "table.md").read_text()


def test_a_stale_arm_is_refused_when_it_would_train(tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    write_fake_run(str(out / "scratch"), "nicol_lift_reduced", FAKE["scratch"], None, given={"epochs": 3})  # no physics
    assert experiment.main([*EXPERIMENT, "--out", str(out)]) == 2
    assert no_nicol == []  # not even the source, which comes first
    assert capsys.readouterr().err.splitlines() == [
        f"error: {out / 'scratch'} is stale (physics not recorded). Nothing was trained and no run folder changed: "
        "move the stale folders away or pass another --out"
    ]
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "source"]) == 0  # trains only the source
    assert [call[:2] for call in no_nicol] == [("prepare", str(out / "source")), ("train", str(out / "source"))]


def test_the_table_names_the_stale_runs_it_shows(tmp_path, no_nicol, fake_run):
    out = tmp_path / "out"
    fake_run(str(out / "source"), "nicol_slide", FAKE["source"], None)
    fake_run(str(out / "transfer"), "nicol_lift_reduced", FAKE["transfer"], None)
    write_fake_run(str(out / "scratch"), "nicol_lift_reduced", FAKE["scratch"], None, given={"epochs": 3})  # no physics
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "none"]) == 0
    table = (out / "table.md").read_text()
    assert "| scratch | 2 | 3 | 300 |" in table
    assert f"\n\nStale: scratch, {grid.STALE_WHY}. Their figures here are not today's experiment.\n\n" in table


def test_the_transfer_arm_refuses_a_stale_source(tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    write_fake_run(str(out / "source"), "nicol_slide", FAKE["source"], None, given={"epochs": 2})  # no physics
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "transfer"]) == 2
    assert no_nicol == []
    assert capsys.readouterr().err.splitlines() == [
        f"error: {out / 'source'} is stale (physics not recorded). Nothing was trained and no run folder changed: "
        "move the stale folders away or pass another --out"
    ]


@pytest.mark.parametrize("source_rows", [0, 1])  # no source run; one interrupted at epoch 1 of 2
def test_the_transfer_arm_refuses_to_start_from_an_unfinished_source(source_rows, tmp_path, no_nicol, fake_run,
                                                                       capsys):
    out = tmp_path / "out"
    if source_rows:
        fake_run(str(out / "source"), "nicol_slide", FAKE["source"][:source_rows], source_rows)
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "transfer"]) == 2
    assert no_nicol == []
    assert capsys.readouterr().err.splitlines() == [
        f"error: --arms transfer: its source {out / 'source'} is at epoch {source_rows} of 2, and the transfer arm "
        "starts from its parameters. Nothing was trained: finish the source first (--arms source)"
    ]
    assert experiment.main([*EXPERIMENT, "--out", str(out), "--arms", "source,transfer"]) == 0  # source first
    assert [call[:2] for call in no_nicol] == [
        ("prepare", str(out / "source")), ("train", str(out / "source")),
        ("prepare", str(out / "transfer")), ("train", str(out / "transfer")),
    ]


def test_arms_share_seeds_and_settings_and_start_held_unless_the_plain_variant():
    args, rest = experiment.build_parser().parse_known_args(["--seeds", "5", "--num-envs", "64"])
    arms = experiment.make_arms(args, grid.pass_through(rest, experiment.PROG), "out")
    assert [a.name for a in arms] == ["source", "transfer", "scratch"]
    source, moved, scratch = (a.given for a in arms)
    assert (source["env"], source["epochs"], source["num_envs"]) == ("nicol_slide", 30, 64)
    assert "exploration_starts" not in source  # nicol_slide has no held start
    assert {k: v for k, v in moved.items() if k not in ("init_from", "init_parts", "init_normaliser", "run_dir")} == {
        k: v for k, v in scratch.items() if k != "run_dir"
    }
    assert (scratch["seeds"], moved["init_from"]) == (5, "out/source")
    # both arms train under the lifting preset's held starts, evaluated from reset
    assert [a.config.train.exploration_starts for a in arms] == [0.0, 0.5, 0.5]
    assert moved["init_normaliser"] == "fresh"  # the target task's statistics, unless --init-normaliser inherit
    args, _ = experiment.build_parser().parse_known_args(["--init-normaliser", "inherit"])
    assert experiment.make_arms(args, {}, "out")[1].given["init_normaliser"] == "inherit"
    args, rest = experiment.build_parser().parse_known_args(["--source", "runs/slide", "--source-checkpoint", "best"])
    arms = experiment.make_arms(args, grid.pass_through(rest, experiment.PROG), "out")
    assert [a.name for a in arms] == ["transfer", "scratch"] and arms[0].given["init_from"] == "runs/slide:best"
    args, rest = experiment.build_parser().parse_known_args(["--exploration-starts", "0"])
    plain = experiment.make_arms(args, grid.pass_through(rest, experiment.PROG), "out")
    assert [a.config.train.exploration_starts for a in plain] == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    "extra, expected",
    [
        (["--env", "ur5_reach"], "error: --env: not passed through to the runs (the experiment sets it)"),
        (["--num-envs", "0"], "error: --num-envs 0: must be a positive integer"),
        (
            ["--arms", "source,lift"],
            "error: --arms source,lift: unknown arm 'lift'; allowed: source, transfer, scratch",
        ),
    ],
)
def test_bad_experiment_options_are_refused_before_anything_runs(extra, expected, tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    assert experiment.main([*EXPERIMENT, "--out", str(out), *extra]) == 2
    assert capsys.readouterr().err.strip() == expected
    assert no_nicol == [] and not out.exists()
