"""The learning-curve grid (experiments/paper/curves.py) on hand-written run directories, without
training (`no_nicol` and `write_fake_run` of conftest.py): the plan and its estimate, one budget per
task, seed blocks, resuming, stale runs, refusals, the plain lifting variant and the report."""

import csv
import json
import math
import os
import shlex

import jax
import pytest

import envs_mjx
from bidal_jax import config as config_lib
from bidal_jax.run import loop
from experiments import report
from experiments.paper import curves, grid, protocol
from tests.conftest import TODAY, write_fake_run
from tests.helpers import REPO

TASKS = ("planar_reach", "ur5_reach", "nicol_slide", "nicol_lift")
SMALL = ["--tasks", "planar_reach", "--agents", "proprio_baseline,visual_baseline,multimodal_baseline",
         "--seeds", "2", "--epochs", "3", "--quiet"]
DONE = [(0.1, 0.3), (0.5, 0.7), (0.7, 0.9)]  # 3 epochs of 2 seeds: a finished run of SMALL


@pytest.fixture(autouse=True)
def no_floors(monkeypatch):
    """The tables without the stored floors (results/floors), so that their cells are the figures alone; the test
    of the floors' marks gives its own."""
    monkeypatch.setattr(report, "load_floors", lambda folder=report.FLOORS: {})


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
    return grid.curve_arms(TASKS, tuple(config_lib.AGENTS), args.seeds, args.seed, args.epochs,
                           grid.pass_through(rest, curves.PROG), out)


def test_the_grid_is_the_papers_tasks_and_agents():
    assert protocol.paper_tasks() == TASKS and set(TASKS) < set(envs_mjx.names())  # nicol_lift_reduced is not in it
    arms = _arms([])
    assert [a.name for a in arms[:6]] == [f"planar_reach/{agent}" for agent in config_lib.AGENTS]
    assert len(arms) == 24 and arms[-1].run_dir == os.path.join("out", "nicol_lift", "multimodal_bidal_no_ri")


@pytest.mark.parametrize("argv, expected", [
    ([], {"planar_reach": 100, "ur5_reach": 150, "nicol_slide": 30, "nicol_lift": 25}),
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
        lines[0] == "plan: 24 runs" and len([line for line in lines if line.endswith(" s") and "[new]" in line]) == 24
    )
    for task in TASKS:
        for agent in config_lib.AGENTS:
            assert (
                f"{task} {agent}, 5 seed(s), exploration starts {0.5 if task == 'nicol_lift' else 0:g}; " in printed
                and f"{out}/{task}/{agent} [new]" in printed
            )
    assert (
        f"nicol_lift visual_bidal, 5 seed(s), exploration starts 0.5; 25 epochs × 204,800 = 5,120,000 env steps "
        f"per seed in {out}/nicol_lift/visual_bidal [new]; estimated 523 s"  # 81.2 s + 25 × 17.68 s
    ) in lines
    assert (
        f"ur5_reach proprio_baseline, 5 seed(s), exploration starts 0; 150 epochs × 8,000 = 1,200,000 env steps per "
        f"seed in {out}/ur5_reach/proprio_baseline [new]; estimated 118 s"  # 29.5 s + 150 × 0.59 s
    ) in lines
    # the reaching tasks (1 + 5 image agents), then (proprio, 2 baselines and 3 BidAL agents) on nicol_slide and
    # nicol_lift, from the sweeps' unrounded figures: (100 + 5 × 167.2) + (118 + 5 × 221.4) + (212.7 + 2 × 214.9
    # + 3 × 264.4) + (158.9 + 2 × 508.1 + 3 × 523.2)
    assert "estimated time: 6,338 s (1.8 h) on one GPU running the runs one after another" in printed
    assert "not measured" not in printed  # every task of the grid has its sweeps
    assert lines[-1] == "dry run: nothing trained or written"


@pytest.mark.parametrize("task", TASKS)
def test_the_estimates_read_the_measured_epochs_in_results(task):
    """Each agent's estimate is its stand-in's sweep in results/scaling/epochs (5 seeds, 3 epochs): the mean step of
    `process_seconds` per epoch, and the first epoch's `variant_seconds` less one epoch."""
    for agent in config_lib.AGENTS:
        timed, stand_in = grid.epoch_time(task, agent), grid.timed_agent(task, agent, grid.measured_epochs())
        with open(os.path.join(REPO, "results", "scaling", "epochs", f"{task}-{stand_in}.jsonl")) as f:
            rows = [json.loads(line) for line in f]
        assert {row["engine"] for row in rows} == {"warp" if task.startswith("nicol") else "jax"}
        assert [row["epoch"] for row in rows] == [1, 2, 3] and {row["variant"] for row in rows} == {"preset"}
        per_epoch = (rows[-1]["process_seconds"] - rows[0]["process_seconds"]) / 2
        assert timed == (pytest.approx(per_epoch), pytest.approx(rows[0]["variant_seconds"] - per_epoch), task)


def test_each_agent_takes_its_stand_ins_sweep():
    measured = grid.measured_epochs()
    assert [grid.timed_agent("nicol_lift", agent, measured) for agent in config_lib.AGENTS] == [
        "proprio_baseline", "multimodal_baseline", "multimodal_baseline", "multimodal_bidal", "multimodal_bidal",
        "multimodal_bidal"]
    assert {grid.timed_agent("planar_reach", agent, measured) for agent in config_lib.AGENTS
            if agent != "proprio_baseline"} == {"multimodal_bidal"}


def test_a_task_without_a_sweep_is_estimated_as_the_longest_measured_epoch_and_nothing_measured_as_unknown(
        tmp_path, monkeypatch):
    """No KeyError for a task that results/ has not timed: a labelled variant (nicol_lift_reduced, nicol_slide_ee)
    as its base task, a new task as the longest measured epoch of its stand-in agent; where results/ is missing, no
    estimate, and a cell is one block of all its seeds."""
    longest = max(grid.epoch_time(task, "multimodal_bidal") for task in TASKS)
    assert longest.task == "nicol_lift"
    assert grid.epoch_time("unknown_task", "visual_baseline") == longest  # no baseline sweep of its own
    # a labelled variant is timed as the task it derives from, with that task's stand-in agent
    lift = grid.epoch_time("nicol_lift", "multimodal_bidal")
    assert grid.epoch_time("nicol_lift_reduced", "multimodal_bidal") == lift
    slide = grid.epoch_time("nicol_slide", "visual_baseline")
    assert grid.epoch_time("nicol_slide_ee", "multimodal_baseline") == slide and slide.task == "nicol_slide"
    assert grid.epoch_time("nicol_lift", "proprio_baseline", str(tmp_path)) is None
    cell = next(a for a in _arms(["--seeds", "50"]) if a.name == "nicol_lift/visual_bidal")
    assert len(grid.blocks(cell)) > 1
    monkeypatch.setattr(grid, "measured_epochs", lambda folder: {})
    assert grid.blocks(cell) == [cell] and math.isnan(grid.estimate(cell, grid.Status("new", None, None)))


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
            "error: --tasks foo: unknown task 'foo'; allowed: planar_reach, ur5_reach, nicol_slide, nicol_lift, "
            "nicol_lift_reduced, nicol_slide_ee, nicol_slide_ee_obj",
        ),
        (  # a registered task without a learning-curve budget needs --epochs
            ["--tasks", "nicol_slide,nicol_lift_reduced"],
            "error: --tasks nicol_slide,nicol_lift_reduced: nicol_lift_reduced declares no learning-curve budget "
            "(its env's task.paper_epochs); give --epochs N",
        ),
        (["--tasks", ","], "error: --tasks ',': name at least one of planar_reach, ur5_reach, nicol_slide, nicol_lift, "
         "nicol_lift_reduced, nicol_slide_ee, nicol_slide_ee_obj"),
        (
            ["--agents", "proprio_baseline,bidal"],
            "error: --agents proprio_baseline,bidal: unknown agent 'bidal'; allowed: "
            "proprio_baseline, visual_baseline, multimodal_baseline, visual_bidal, multimodal_bidal, "
            "multimodal_bidal_no_ri",
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


def test_lifting_starts_held_by_default_and_the_plain_variant_writes_elsewhere(tmp_path, monkeypatch, no_nicol,
                                                                               capsys):
    held, plain = _arms([]), _arms(["--exploration-starts", "0"])
    for a, b in zip(held, plain):
        assert a.config.train.exploration_starts == (0.5 if a.given["env"] == "nicol_lift" else 0.0), a.name
        assert b.config.train.exploration_starts == 0.0
    monkeypatch.chdir(tmp_path)
    assert curves.main(["--exploration-starts", "0", "--dry-run"]) == 0
    printed = capsys.readouterr().out
    assert "nicol_lift multimodal_bidal, 5 seed(s), exploration starts 0; " in printed
    assert "results/curves-plain/nicol_lift/multimodal_bidal [new]" in printed and "results/curves/" not in printed
    assert curves.main(["--tasks", "nicol_lift", "--dry-run"]) == 0
    assert "nicol_lift multimodal_bidal, 5 seed(s), exploration starts 0.5; " in capsys.readouterr().out
    assert not (tmp_path / "results").exists()


def test_a_cell_longer_than_a_block_is_split_into_blocks_of_its_seeds():
    """A cell is one run where its estimate fits `BLOCK_SECONDS`, else blocks of as even seeds as can be, each a run
    of its own first seed in its own folder, each estimated within the limit."""
    def visual_bidal(argv):
        return next(a for a in _arms(argv) if a.name == "nicol_lift/visual_bidal")

    fits = visual_bidal([])
    assert grid.blocks(fits) == [fits]
    cell = visual_bidal(["--seeds", "10", "--epochs", "100", "--seed", "7"])
    blocks = grid.blocks(cell)
    assert [b.given["seeds"] for b in blocks] == [3, 3, 2, 2]
    assert [b.given["seed"] for b in blocks] == [7, 10, 13, 15]
    assert [b.run_dir for b in blocks] == [os.path.join(cell.run_dir, f"seeds-{a}-{z}")
                                           for a, z in ((0, 2), (3, 5), (6, 7), (8, 9))]
    assert [b.name for b in blocks][0] == "nicol_lift/visual_bidal/seeds-0-2"
    new = grid.Status("new", None, None)
    assert grid.estimate(cell, new) > grid.BLOCK_SECONDS
    assert all(grid.estimate(b, new) <= grid.BLOCK_SECONDS for b in blocks)


def test_merging_two_seed_blocks_gives_the_table_of_one_run_of_all_the_seeds(tmp_path, no_nicol, fake_run, capsys):
    """A cell stored as two blocks of seeds (their metrics and configs alone) reads, plots and tabulates as one run
    of all its seeds; only its time is the blocks' sum."""
    rows = [(0.1, 0.3, 0.0, 1.0), (0.5, 0.7, 0.2, 1.0), (0.7, 0.9, 0.4, 1.0)]
    argv = ["--tasks", "planar_reach", "--agents", "proprio_baseline", "--seeds", "4", "--epochs", "3",
            "--last-n", "2", "--report"]
    one, two = tmp_path / "one", tmp_path / "two"
    fake_run(str(one / "planar_reach" / "proprio_baseline"), "planar_reach", rows, None, agent="proprio_baseline",
             given={"seed": 0}, compile_seconds=5.0)
    for first, last in ((0, 1), (2, 3)):
        fake_run(str(two / "planar_reach" / "proprio_baseline" / f"seeds-{first}-{last}"), "planar_reach",
                 [r[first:last + 1] for r in rows], None, agent="proprio_baseline", given={"seed": first},
                 compile_seconds=5.0)
    assert curves.main([*argv, "--out", str(one)]) == 0 and curves.main([*argv, "--out", str(two)]) == 0
    assert (one / "curves.csv").read_text() == (two / "curves.csv").read_text()
    tables = [(out / "table.md").read_text().replace(str(out), "OUT") for out in (one, two)]
    # each block's 30 s + 5 s of compile, summed
    assert tables[0].replace("35 s (0.6 min)", "70 s (1.2 min)").replace("35 s", "70 s") == tables[1]
    assert "| proprio_baseline | 0.675 ± 0.259, 70 s |" in tables[1] and "†" not in tables[1]
    assert "No run is missing or unfinished." in tables[1]


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
    # machine time: each run alone on a machine without a recorded GPU count (1)
    assert "the runs held: 140 s (2.3 min) of GPU time" in table and "summed process time: 140 s (2.3 min)." in table
    assert "| floor: a policy that does nothing | not computed | not computed |" in table
    assert "†" not in table  # no run is stale
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
    assert grid.stale(arm, TODAY) == ("config differs: epochs 100 → 30, num_envs 512 → 2560, cycles_per_epoch 5 → 1, "
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
    assert table.index("| multimodal_bidal |") < table.index("† stale") < table.index("Machine time")


def test_runs_resumed_with_an_empty_buffer_are_named_below_the_table():
    configs = {"nicol_lift/multimodal_bidal": {"fresh_buffer_epochs": [35, 70]}, "nicol_lift/proprio_baseline": {}}
    note = grid.fresh_buffer_note(configs)
    assert note[0].endswith("(`--resume --fresh-buffer`, a deviation from an uninterrupted run: the next epochs learn "
                            "from fresh episodes only): nicol_lift/multimodal_bidal after epochs 35, 70.")
    assert grid.fresh_buffer_note({"nicol_lift/proprio_baseline": {"fresh_buffer_epochs": []}}) == []


def test_cells_say_how_many_seeds_are_above_the_floor(tmp_path, fake_run, monkeypatch):
    floors = {"planar_reach": {"all": report.Floor(0.5, 0.001, 1.0)}}
    monkeypatch.setattr(report, "load_floors", lambda folder=report.FLOORS: floors)
    out = tmp_path / "out"
    # seed 0 at 0.9 (of 64 eval episodes an epoch: far above 0.5), seed 1 at 0.5 (the floor itself)
    fake_run(str(out / "planar_reach" / "proprio_baseline"), "planar_reach", [(0.9, 0.5)] * 3, None,
             agent="proprio_baseline")
    assert curves.main(["--report", "--tasks", "planar_reach", "--agents", "proprio_baseline", "--seeds", "2",
                        "--epochs", "3", "--out", str(out)]) == 0
    table = (out / "table.md").read_text()
    assert "| proprio_baseline | 0.700 ± 0.200 (last 3) (1/2 above its floor), 30 s*" in table
    assert "| floor: a policy that does nothing | 0.500 |" in table
