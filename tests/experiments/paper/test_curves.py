"""The learning-curve grid (experiments/paper/curves.py) on hand-written run directories, without
training (`no_nicol` and `write_fake_run` of conftest.py): the plan and its estimate, one budget per
task, resuming, stale runs, refusals, the held-starts variant and the report."""

import csv
import json
import os
import shlex

import jax
import pytest

import envs_mjx
from bidal_jax import config as config_lib
from bidal_jax.run import loop
from experiments.paper import curves, grid
from tests.conftest import TODAY, write_fake_run
from tests.helpers import REPO

TASKS = ("planar_reach", "ur5_reach", "nicol_slide", "nicol_lift")
SMALL = ["--tasks", "planar_reach", "--agents", "proprio_baseline,visual_baseline,multimodal_baseline",
         "--seeds", "2", "--epochs", "3", "--quiet"]
DONE = [(0.1, 0.3), (0.5, 0.7), (0.7, 0.9)]  # 3 epochs of 2 seeds: a finished run of SMALL


@pytest.fixture
def fake_run():
    """`write_fake_run` of a run made today for its arm of `SMALL` or `REPORT` (3 epochs): on today's physics
    (`no_nicol`'s), with the arm's config; `physics` and `given` (more config fields) make it another."""
    def write(run_dir, env, rows, checkpoint_epoch, physics=(TODAY,), given=(), **kwargs):
        write_fake_run(run_dir, env, rows, checkpoint_epoch, physics=None if physics is None else list(physics),
                       given={"epochs": 3, **dict(given)}, **kwargs)
    return write


def _arms(argv, out="out"):
    args, rest = curves.build_parser().parse_known_args(argv)
    return curves.make_arms(TASKS, tuple(config_lib.AGENTS), args, grid.pass_through(rest, curves.PROG), out)


def test_the_grid_is_the_papers_tasks_and_agents():
    assert curves.TASKS == TASKS and set(TASKS) < set(envs_mjx.names())  # nicol_lift_reduced is not in it
    arms = _arms([])
    assert [a.name for a in arms[:5]] == [f"planar_reach/{agent}" for agent in config_lib.AGENTS]
    assert len(arms) == 20 and arms[-1].run_dir == os.path.join("out", "nicol_lift", "multimodal_bidal")


@pytest.mark.parametrize("argv, expected", [
    ([], {"planar_reach": 100, "ur5_reach": 150, "nicol_slide": 100, "nicol_lift": 100}),
    (["--epochs", "7"], dict.fromkeys(TASKS, 7)),
])
def test_every_agent_of_a_task_gets_the_same_epochs(argv, expected):
    arms = _arms([*argv, "--num-envs", "64"])
    for task, epochs in expected.items():
        configs = [a.config for a in arms if a.given["env"] == task]
        # the resolved configs: no image-agent preset overrides the task's budget
        assert {config.run.epochs for config in configs} == {epochs}
        assert {config.train.num_envs for config in configs} == {64}  # learner options pass to every run


def test_dry_run_lists_every_run_and_the_estimate_and_writes_nothing(tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    assert curves.main(["--dry-run", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert not out.exists() and no_nicol == []
    lines = printed.splitlines()
    assert (
        lines[0] == "plan: 20 runs" and len([line for line in lines if line.endswith(" s") and "[new]" in line]) == 20
    )
    for task in TASKS:
        for agent in config_lib.AGENTS:
            assert (
                f"{task} {agent}, {10 if task == 'nicol_lift' else 5} seed(s), exploration starts 0; " in printed
                and f"{out}/{task}/{agent} [new]" in printed
            )
    assert (
        f"nicol_lift visual_bidal, 10 seed(s), exploration starts 0; 100 epochs × 204,800 = 20,480,000 env steps "
        f"per seed in {out}/nicol_lift/visual_bidal [new]; estimated 3,617 s"  # 81.2 s + 100 × 17.68 s × 10 / 5
    ) in lines
    assert (
        f"ur5_reach proprio_baseline, 5 seed(s), exploration starts 0; 150 epochs × 8,000 = 1,200,000 env steps per "
        f"seed in {out}/ur5_reach/proprio_baseline [new]; estimated 118 s"  # 29.5 s + 150 × 0.59 s
    ) in lines
    # the reaching tasks (1 + 4 agents), then (proprio, 2 baselines and 2 BidAL agents) on nicol_slide and, at
    # 10 seeds, nicol_lift: (100 + 4 × 167.5) + (118 + 4 × 221.6) + (360.4 + 2 × 547.4 + 2 × 681.6)
    # + (979.6 + 2 × 2,793.6 + 2 × 3,617.2)
    assert "estimated time: 18,394 s (5.1 h) on one GPU running the runs one after another" in printed
    assert lines[-1] == "dry run: nothing trained or written"


@pytest.mark.parametrize("task", TASKS)
def test_the_estimates_are_the_measured_epochs_in_results(task):
    """Each `SECONDS` entry is its sweep's in results/scaling/epochs (5 seeds, 3 epochs): the mean step of
    `process_seconds` per epoch, and the first epoch's `variant_seconds` less one epoch, so the estimate follows
    the measurements, not copied figures."""
    measured = {"image": "multimodal_bidal", "image_baseline": "multimodal_baseline", "proprio": "proprio_baseline"}
    for kind, seconds in grid.SECONDS[task].items():
        with open(os.path.join(REPO, "results", "scaling", "epochs", f"{task}-{measured[kind]}.jsonl")) as f:
            rows = [json.loads(line) for line in f]
        assert {row["engine"] for row in rows} == {"warp" if task.startswith("nicol") else "jax"}
        assert [row["epoch"] for row in rows] == [1, 2, 3] and {row["variant"] for row in rows} == {"preset"}
        per_epoch = (rows[-1]["process_seconds"] - rows[0]["process_seconds"]) / 2
        assert seconds == pytest.approx((per_epoch, rows[0]["variant_seconds"] - per_epoch), abs=0.05)


def test_each_agent_takes_its_kinds_estimate():
    assert [grid.kind("nicol_lift", agent) for agent in config_lib.AGENTS] == [
        "proprio", "image_baseline", "image_baseline", "image", "image"]
    assert {grid.kind("planar_reach", agent) for agent in config_lib.AGENTS if agent != "proprio_baseline"} == {"image"}


def test_done_runs_are_skipped_interrupted_resumed_and_unstarted_started_again(tmp_path, no_nicol, fake_run, capsys):
    out = tmp_path / "out"
    done, interrupted, unstarted = (
        str(out / "planar_reach" / a) for a in ("proprio_baseline", "visual_baseline", "multimodal_baseline")
    )
    # finished, its checkpoints not kept (as in results/): its metrics hold all its epochs
    fake_run(done, "planar_reach", DONE, None, agent="proprio_baseline")
    fake_run(interrupted, "planar_reach", [(0.2, 0.2)], 1, agent="visual_baseline")
    os.makedirs(unstarted)
    with open(os.path.join(unstarted, "metrics.csv"), "w") as f:
        f.write("epoch\n")  # stopped before its first checkpoint
    assert curves.main([*SMALL, "--out", str(out), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert no_nicol == []
    assert "[done]; estimated 0 s" in printed
    # 55.5 s compile + 2 epochs × 1.12 s at 5 seeds, × 2 / 5 at SMALL's 2 seeds; a new run: 3 epochs
    assert "[resume, checkpoint at epoch 1]; estimated 56 s" in printed
    assert "[new]; estimated 57 s" in printed
    assert curves.main([*SMALL, "--out", str(out)]) == 0
    assert no_nicol == [
        ("prepare", interrupted, True, False),
        ("train", interrupted, True, False),
        ("prepare", unstarted, False, True),
        ("train", unstarted, False, False),
    ]
    assert f"planar_reach/proprio_baseline: done ({done})" in capsys.readouterr().out
    assert "| proprio_baseline | 0.533 ± 0.100 (last 3), 30 s* |" in (out / "table.md").read_text()  # seeds 0.43, 0.63


def test_a_run_without_its_buffer_is_refused_unless_fresh_buffer_resumes_it_with_an_empty_one(
        tmp_path, no_nicol, fake_run, monkeypatch, capsys):
    out = tmp_path / "out"
    bare, kept = (str(out / "planar_reach" / a) for a in ("visual_baseline", "proprio_baseline"))
    fake_run(bare, "planar_reach", [(0.2, 0.2)], 1, agent="visual_baseline", buffer=False)  # its buffer deleted
    fake_run(kept, "planar_reach", [(0.2, 0.2)], 1, agent="proprio_baseline")
    assert curves.main([*SMALL, "--out", str(out), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert f"{bare} [resume, checkpoint at epoch 1 without its replay buffer]" in printed
    assert f"{kept} [resume, checkpoint at epoch 1]" in printed
    fresh, train = [], loop.train  # no_nicol's

    def record(env, config, **kwargs):
        fresh.append((config.run.run_dir, kwargs["fresh_buffer"]))
        return train(env, config, **kwargs)

    monkeypatch.setattr(loop, "train", record)
    assert curves.main([*SMALL, "--out", str(out)]) == 2  # the default path never drops a buffer
    assert fresh == [(kept, False)]
    assert f"error: {bare}: its latest checkpoint has no replay buffer; --fresh-buffer resumes it" in (
        capsys.readouterr().err)
    assert curves.main([*SMALL, "--out", str(out), "--fresh-buffer"]) == 0
    assert (bare, True) in fresh and fresh.count((kept, False)) == 2
    assert "visual_baseline: its checkpoint has no replay buffer: resuming with an empty one (--fresh-buffer" in (
        capsys.readouterr().out)


def test_training_compiles_into_the_runs_persistent_cache(tmp_path, monkeypatch, no_nicol):
    """A resumed cell on a fresh machine finds its program in the cache carried there ($BIDAL_JAX_CACHE)."""
    monkeypatch.setenv("BIDAL_JAX_CACHE", str(tmp_path / "cache"))
    keys = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")
    kept = {key: getattr(jax.config, key) for key in keys}
    try:
        assert curves.main([*SMALL, "--out", str(tmp_path / "out")]) == 0
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cache")
    finally:
        for key, value in kept.items():
            jax.config.update(key, value)


@pytest.mark.parametrize(
    "extra, expected",
    [
        (
            ["--tasks", "foo"],
            "error: --tasks foo: unknown task 'foo'; allowed: planar_reach, ur5_reach, nicol_slide, nicol_lift",
        ),
        (
            ["--tasks", "nicol_slide,nicol_lift_reduced"],
            "error: --tasks nicol_slide,nicol_lift_reduced: unknown task "
            "'nicol_lift_reduced'; allowed: planar_reach, ur5_reach, nicol_slide, nicol_lift",
        ),
        (["--tasks", ","], "error: --tasks ',': name at least one of planar_reach, ur5_reach, nicol_slide, nicol_lift"),
        (
            ["--agents", "proprio_baseline,bidal"],
            "error: --agents proprio_baseline,bidal: unknown agent 'bidal'; allowed: "
            "proprio_baseline, visual_baseline, multimodal_baseline, visual_bidal, multimodal_bidal",
        ),
        # the pass-through options are experiments/paper/grid.py's (tested in full with transfer_learning)
        (["--env", "ur5_reach"], "error: --env: not passed through to the runs (the experiment sets it)"),
        (["--last-n", "0"], "error: --last-n 0: must be a positive integer"),
    ],
)
def test_bad_options_are_refused_before_anything_is_written(extra, expected, tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    assert curves.main(["--out", str(out), *extra]) == 2
    assert capsys.readouterr().err.strip() == expected
    assert no_nicol == [] and not out.exists()


def test_held_starts_changes_only_nicol_lift_and_writes_elsewhere(tmp_path, monkeypatch, no_nicol, capsys):
    plain, held = _arms([]), _arms(["--held-starts"])
    for a, b in zip(plain, held):
        changed = {k for k in a.given.keys() | b.given.keys() if a.given.get(k) != b.given.get(k)}
        assert changed == ({"exploration_starts"} if a.given["env"] == "nicol_lift" else set()), a.name
        assert b.given.get("exploration_starts", 0.5) == 0.5
    monkeypatch.chdir(tmp_path)
    assert curves.main(["--held-starts", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "nicol_lift multimodal_bidal, 10 seed(s), exploration starts 0.5; " in printed
    assert "nicol_slide multimodal_bidal, 5 seed(s), exploration starts 0; " in printed
    assert "results/curves-held/nicol_lift/multimodal_bidal [new]" in printed and "results/curves/" not in printed
    assert not (tmp_path / "results").exists()


REPORT = [
    "--tasks",
    "planar_reach,ur5_reach",
    "--agents",
    "proprio_baseline,multimodal_bidal",
    "--seeds",
    "2",
    "--epochs",
    "3",
    "--last-n",
    "2",
    "--report",
]


def test_report_writes_the_plot_and_table_from_run_folders_without_checkpoints(tmp_path, no_nicol, fake_run, capsys):
    out = tmp_path / "out"
    assert curves.main([*REPORT, "--out", str(out)]) == 0
    assert "no epochs yet: nothing to plot" in capsys.readouterr().out and not out.exists()
    written = {
        ("planar_reach", "proprio_baseline"): ([(0.1, 0.3), (0.5, 0.7), (0.7, 0.9)], None),
        ("planar_reach", "multimodal_bidal"): ([(0.2, 0.2), (0.4, 0.6)], 60.0),  # with wall_time_with_compile
        ("ur5_reach", "proprio_baseline"): ([(1.0, 0.0), (1.0, 0.0), (1.0, 1.0)], None),
    }
    for (task, agent), (rows, compile_seconds) in written.items():
        fake_run(str(out / task / agent), task, rows, None, agent=agent, compile_seconds=compile_seconds)
    assert curves.main([*REPORT, "--out", str(out)]) == 0
    assert no_nicol == []
    table = (out / "table.md").read_text()
    # last 2 epochs per seed: planar proprio 0.6, 0.8; planar multimodal 0.3, 0.4; ur5 proprio 1.0, 0.5
    assert "| agent | planar_reach (3 epochs) | ur5_reach (3 epochs) |" in table
    # runs recorded before wall_time_with_compile show their wall_time, marked; the other its time with compile
    assert "| proprio_baseline | 0.700 ± 0.100, 30 s* | 0.750 ± 0.250, 30 s* |" in table
    assert "| multimodal_bidal | 0.350 ± 0.050, 80 s, epoch 2 of 3 | — |" in table
    assert "Total wall time of the runs: 140 s (2.3 min)." in table and "†" not in table  # no run is stale
    assert "Missing: ur5_reach/multimodal_bidal. Unfinished: planar_reach/multimodal_bidal (epoch 2 of 3)." in table
    # the last line is the command that writes the same table again from the run folders
    command = table.splitlines()[-1]
    assert command == (f"Regenerate from the run folders: `python -m experiments.paper.curves --report --tasks "
                       f"planar_reach,ur5_reach --agents proprio_baseline,multimodal_bidal --seeds 2 --epochs 3 "
                       f"--last-n 2 --out {out}`")
    (out / "table.md").unlink()
    assert curves.main(shlex.split(command.split("`")[1])[3:]) == 0
    assert (out / "table.md").read_text() == table
    with open(out / "curves.png", "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    with open(out / "curves.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert {(r["panel"], r["label"]) for r in rows} == {
        ("planar_reach", "proprio_baseline"),
        ("planar_reach", "multimodal_bidal"),
        ("ur5_reach", "proprio_baseline"),
    }
    first = rows[0]  # planar_reach proprio_baseline, epoch 1: seeds 0.1 and 0.3 after 100 env steps per seed
    assert (float(first["x"]), float(first["mean"]), float(first["std"])) == pytest.approx((100, 0.2, 0.1))


def test_a_finished_grid_says_so():
    arms = _arms(["--epochs", "2"])[:1]
    runs = {arms[0].name: {"epoch": [1.0, 2.0]}}
    assert grid.gaps(arms, runs) == "No run is missing or unfinished."


def test_a_run_whose_metrics_lack_an_epoch_is_named():
    arms = _arms(["--epochs", "4"])[:1]
    runs = {arms[0].name: {"epoch": [1.0, 2.0, 4.0]}}
    assert grid.gaps(arms, runs) == (
        f"No run is missing or unfinished. Epochs without a row in metrics.csv: {arms[0].name} (3); "
        "the final success averages the last rows there are."
    )


@pytest.mark.parametrize("physics, given, expected", [
    ((TODAY,), {}, None),
    # what cannot change results: where the run is written, its checkpoint cadence, its device layout, its convs'
    # implementation
    ((TODAY,), {"checkpoint_every": 1, "env_shards": 2, "conv_impl": "banded"}, None),
    ((TODAY,), {"conv_impl": "taps"}, None),  # an implementation removed since: the same function as patch
    (("old",), {}, "trained on other physics"),
    (("old", TODAY), {}, "trained on other physics"),  # resumed after a model change
    (None, {}, "physics not recorded"),  # older than the record
    ((TODAY,), {"num_envs": 512, "batch_size": 64}, "config differs: num_envs 512 → 16, batch_size 64 → 256"),
    ((TODAY,), {"epochs": 5}, "config differs: epochs 5 → 3"),  # a run made for another budget
    (None, {"critic_lr": 0.01}, "physics not recorded; config differs: critic_lr 0.01 → 0.001"),
])
def test_a_run_on_other_physics_or_with_another_config_is_stale(physics, given, expected, tmp_path, fake_run):
    arm = _arms(SMALL, str(tmp_path))[0]  # planar_reach proprio_baseline, 2 seeds, 3 epochs
    assert grid.status(arm, TODAY) == ("new", None, None)  # no folder: never stale
    fake_run(arm.run_dir, "planar_reach", DONE, None, agent="proprio_baseline", physics=physics, given=given)
    assert grid.stale(arm, TODAY) == expected
    assert grid.status(arm, TODAY) == (("done", 3, None) if expected is None else ("stale", 3, expected))


def test_a_run_of_an_older_nicol_preset_is_stale(tmp_path, fake_run):
    arm = next(a for a in _arms(["--seeds", "2"], str(tmp_path)) if a.name == "nicol_slide/proprio_baseline")
    old = {"epochs": 100, "num_envs": 512, "cycles_per_epoch": 5, "updates_per_cycle": 80, "buffer_episodes": 16384}
    fake_run(arm.run_dir, "nicol_slide", DONE, None, agent="proprio_baseline", given=old)
    assert grid.stale(arm, TODAY) == ("config differs: num_envs 512 → 2560, cycles_per_epoch 5 → 1, "
                                      "updates_per_cycle 80 → 1600, buffer_episodes 16384 → 15360")


def test_training_refuses_stale_runs_before_any_trains(tmp_path, no_nicol, fake_run, capsys):
    out = tmp_path / "out"
    new, old, other = (str(out / "planar_reach" / a) for a in ("proprio_baseline", "visual_baseline",
                                                               "multimodal_baseline"))
    fake_run(old, "planar_reach", DONE[:1], 1, agent="visual_baseline", physics=("old",))  # would resume
    fake_run(other, "planar_reach", DONE, None, agent="multimodal_baseline", given={"num_envs": 8})  # would be done
    before = {d: sorted(os.walk(d)) for d in (old, other)}
    assert curves.main([*SMALL, "--out", str(out), "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert f"{old} [stale: trained on other physics]; estimated 57 s" in printed  # counted from the start
    assert f"{other} [stale: config differs: num_envs 8 → 16]; estimated 57 s" in printed
    assert "stale: 2 of 3 runs; training refuses them" in printed
    assert curves.main([*SMALL, "--out", str(out)]) == 2
    assert no_nicol == []  # the first run, new, was not trained either
    assert capsys.readouterr().err.splitlines() == [
        f"error: {old} is stale (trained on other physics); also stale: {other}. Nothing was trained and no run "
        "folder changed: move the stale folders away or pass another --out"
    ]
    assert {d: sorted(os.walk(d)) for d in (old, other)} == before and not os.path.exists(new)


def test_the_table_marks_stale_cells(tmp_path, no_nicol, fake_run):
    out = tmp_path / "out"
    fake_run(str(out / "planar_reach" / "proprio_baseline"), "planar_reach", DONE, None, agent="proprio_baseline")
    fake_run(str(out / "planar_reach" / "multimodal_bidal"), "planar_reach", DONE, None, physics=None)
    fake_run(str(out / "ur5_reach" / "proprio_baseline"), "ur5_reach", DONE, None, agent="proprio_baseline",
             given={"updates_per_cycle": 80})
    assert curves.main([*REPORT, "--out", str(out)]) == 0
    table = (out / "table.md").read_text()
    assert "| proprio_baseline | 0.700 ± 0.100, 30 s* | 0.700 ± 0.100, 30 s*† |" in table
    assert "| multimodal_bidal | 0.700 ± 0.100, 30 s*† | — |" in table
    assert ("\n\n† stale: 2 of 3 cells, runs not recorded on today's physics of their task or made with another "
            "config than their arm's today") in table
    assert table.index("| multimodal_bidal |") < table.index("† stale") < table.index("Total wall time")


def test_runs_resumed_with_an_empty_buffer_are_named_below_the_table():
    configs = {"nicol_lift/multimodal_bidal": {"fresh_buffer_epochs": [35, 70]}, "nicol_lift/proprio_baseline": {}}
    note = grid.fresh_buffer_note(configs)
    assert note[0].endswith("(`--resume --fresh-buffer`, a deviation from an uninterrupted run: the next epochs learn "
                            "from fresh episodes only): nicol_lift/multimodal_bidal after epochs 35, 70.")
    assert grid.fresh_buffer_note({"nicol_lift/proprio_baseline": {"fresh_buffer_epochs": []}}) == []
