"""The pixel agents' ladder (experiments/paper/ladder.py) without training (`no_nicol` and `write_fake_run` of
conftest.py): its cells and plan, bad input, the table with the gap line computed from the runs (Welch's interval,
unfinished and stale cells, a gap that is not there) and the probe's figures, the runs resumed with an empty buffer,
which cells are probed again, and the record its figures.json keeps."""

import json
import os

import numpy as np
import pytest

from bidal_jax.run import checkpoint
from experiments import report
from experiments.paper import ladder, protocol, rungs
from tests.conftest import TODAY, write_fake_run

EXPERIMENT = ["--seeds", "2", "--epochs", "3", "--last-n", "2", "--quiet"]
# each cell's per-epoch, per-seed eval success (2 seeds, 3 epochs); the last 2 epochs make the final
FINAL = {"image": (0.05, 0.05), "ee": (0.3, 0.3), "ee_obj": (0.85, 0.95), "proprio": (0.97, 0.96)}  # baseline, bidal


def fake_ladder(out, rungs=ladder.RUNGS):
    """Finished runs of today's config and physics for every cell of `rungs`, their final success `FINAL`'s."""
    for rung in rungs:
        for agent, final in zip(rung.agents, FINAL[rung.name]):
            rows = [(0.0, 0.1), (final - 0.01, final + 0.01), (final - 0.01, final + 0.01)]
            write_fake_run(str(out / rung.name / agent), rung.env, rows, None, agent=agent, physics=[TODAY],
                           given={"epochs": 3})


def probe_entry(r2):
    """A probe.json entry whose every figure is `r2` (R²) and 1.5 (RMSE, cm), for 2 seeds."""
    figures = {"r2": [[r2] * 3] * 2, "rmse_cm": [[1.5] * 3] * 2}
    per_set = {f: {t: figures for t in ("obj_pos", "ee_pos")} for f in ("phi", "image")}
    return {"run_dir": "x", "step": 3, "episodes": 200, "frames": [8000, 2000], "trained": per_set,
            "random": {f: {t: {**figures, "r2": [[0.1] * 3] * 2} for t in ("obj_pos", "ee_pos")}
                       for f in ("phi", "image")}}


def test_dry_run_lists_every_cell_and_writes_nothing(tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    assert ladder.main(["--dry-run", *EXPERIMENT, "--out", str(out)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "plan: 8 runs" and not out.exists() and no_nicol == []
    for rung in ladder.RUNGS:
        for agent in rung.agents:
            assert any(line.startswith(f"{rung.name}/{agent}: {rung.env} {agent}, 2 seed(s)")
                       and line.endswith("[new]; estimated " + line.rsplit(" ", 2)[-2] + " s") for line in lines)
    assert "probe: 0 cell(s) at their epochs to probe now (200 scripted episodes of frames)" in lines
    assert lines[-1] == "dry run: nothing trained or written"


def test_agents_choose_the_cells_of_the_chosen_rungs(tmp_path, no_nicol, capsys):
    argv = ["--dry-run", *EXPERIMENT, "--rungs", "image,ee", "--agents", "visual_bidal,multimodal_bidal"]
    assert ladder.main([*argv, "--out", str(tmp_path / "out")]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "plan: 2 runs"
    assert [line.split(":")[0] for line in lines[1:3]] == ["image/visual_bidal", "ee/multimodal_bidal"]


def test_each_rung_keeps_its_seeds_unless_seeds_are_given(tmp_path, no_nicol, capsys):
    argv = ["--dry-run", "--rungs", "image,ee", "--agents", "visual_bidal,multimodal_bidal"]
    assert ladder.main([*argv, "--out", str(tmp_path / "out")]) == 0
    lines = capsys.readouterr().out.splitlines()[1:3]
    assert "nicol_slide visual_bidal, 5 seed(s)" in lines[0]
    assert "nicol_slide_ee multimodal_bidal, 3 seed(s)" in lines[1]
    assert [arm.given["seeds"] for arm in rungs.ladder_arms(rungs.RUNGS, 4, 0, None, {}, "out")] == [4] * 8


@pytest.mark.parametrize("argv, expected", [
    (["--rungs", "image,nope"], "error: --rungs image,nope: unknown rung 'nope'; allowed: image, ee, ee_obj, proprio"),
    (["--agents", "visual_bidal,x"], "error: --agents visual_bidal,x: unknown agent 'x'; allowed: visual_baseline, "
                                     "visual_bidal, multimodal_baseline, multimodal_bidal"),
    (["--probe-episodes", "2"], "error: --probe-episodes 2: must be an integer >= 5"),
    (["--env", "nicol_lift"], "error: --env: not passed through to the runs (the experiment sets it)"),
])
def test_bad_input_is_one_line_before_any_work(argv, expected, tmp_path, no_nicol, capsys):
    assert ladder.main([*argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(expected) and err.count("\n") == 1
    assert not (tmp_path / "out").exists() and no_nicol == []


def test_the_table_computes_which_rung_closes_the_gap_and_shows_the_probe(tmp_path, no_nicol):
    out = tmp_path / "out"
    fake_ladder(out)
    (out / "probe.json").write_text(json.dumps({"cells": {"image/visual_baseline": probe_entry(0.5),
                                                          "image/visual_bidal": probe_entry(0.75)}}))
    assert ladder.main(["--report", *EXPERIMENT, "--out", str(out)]) == 0
    assert no_nicol == []  # nothing trained
    table = (out / "table.md").read_text()
    # the floor is nicol_slide's on every rung (results/floors): of 2 × 128 eval episodes, 0.04 is not clearly
    # above 0.031 and 0.06 is
    assert ("| image | nicol_slide | 0.031 | visual_baseline: 0.050 ± 0.010 / 0.050 (0.040, 0.060), 1/2 above its "
            "floor | visual_bidal: 0.050 ± 0.010 / 0.050 (0.040, 0.060), 1/2 above its floor |") in table
    assert "| nicol_slide_ee_obj | 0.031 | multimodal_baseline: 0.850 ± 0.010 / 0.583 (0.840, 0.860), 2/2 ab" in table
    # bidal's ee_obj is 0.01 below proprio, but 2 seeds a cell leave Welch's interval reaching below −0.05
    assert ("baseline: no rung below proprio closes it (ee_obj − proprio -0.120 [-0.181, -0.059]; 0.970 to reach); "
            "bidal: no rung below proprio closes it (ee_obj − proprio -0.010 [-0.071, 0.051]; 0.960 to reach)."
            ) in table
    assert "| image/visual_bidal | trained, step 3 | φ(s) | 0.75, 0.75, 0.75 | 1.5, 1.5, 1.5 |" in table
    assert "| image/visual_bidal | random init | vision branch | 0.10, 0.10, 0.10 |" in table
    assert "No run is missing or unfinished." in table
    assert f"--report --seeds 2 --epochs 3 --last-n 2 --out {out}" in table
    assert (out / "curves.png").exists()
    [section] = json.loads((out / "figures.json").read_text())
    assert section["table"] == "ladder" and section["figure"] == "curves.png"
    assert (section["command"], section["date"]) == (ladder.PROG, ladder.NOT_RUN)  # --report records no command
    assert section["machine"] == "machine not recorded, physics not recorded"
    docs = rungs.docs_table(str(out))  # docs/results.md's: the default cells (3 seeds, the budget): not these runs
    assert docs.count("†") == 8 and docs.count(", epoch 3 of 30") == 8 and ladder.NOT_RUN not in docs
    assert "baseline: not measured (proprio/multimodal_baseline, the level to reach, is not finished)" in docs
    assert ("Linear probe of the visual agents' φ on 2,000 held-out frames (of 40 of 200 scripted episodes; fitted on "
            "the other 8,000 frames), mean over seeds, R² per axis x, y, z (RMSE): visual_baseline obj_pos R² 0.50, "
            "0.50, 0.50 (1.5, 1.5, 1.5 cm)") in docs
    assert "random init obj_pos R² 0.10, 0.10, 0.10 (1.5, 1.5, 1.5 cm)" in docs


def test_without_the_top_rung_no_gap_is_claimed_and_missing_cells_say_not_run(tmp_path, no_nicol):
    out = tmp_path / "out"
    fake_ladder(out, ladder.RUNGS[:2])
    assert ladder.main(["--report", *EXPERIMENT, "--out", str(out)]) == 0
    table = (out / "table.md").read_text()
    assert ("| image + ee_pos + obj_pos | nicol_slide_ee_obj | 0.031 | multimodal_baseline: not run | "
            "multimodal_bidal: not run |") in table
    assert "baseline: not measured (proprio/multimodal_baseline, the level to reach, is not finished)" in table
    assert "Probe: not run." in table and "Missing: ee_obj/multimodal_baseline" in table


def test_a_gap_no_finished_rung_closes_is_not_measured_while_a_rung_below_is_missing(tmp_path, no_nicol):
    out = tmp_path / "out"
    fake_ladder(out, (ladder.RUNGS[0], ladder.RUNGS[-1]))
    assert ladder.main(["--report", *EXPERIMENT, "--out", str(out)]) == 0
    assert ("bidal: not measured (ee, ee_obj not finished); no finished rung below proprio closes it (image − "
            "proprio -0.910 [-0.971, -0.849]; 0.960 to reach).") in (out / "table.md").read_text()


def write_cell(out, rung, agent, finals, epochs=3, physics=TODAY):
    """A run of one cell, of `epochs` of the 3 its arm trains, whose every epoch's per-seed success is `finals`."""
    write_fake_run(str(out / rung.name / agent), rung.env, [tuple(finals)] * epochs, None, agent=agent,
                   physics=[physics], given={"epochs": 3})


def gap(out, finals, stale=()):
    """The gap line of cells whose per-seed finals are `finals` (rung name -> them, the same in both columns; None:
    no run), of 3 epochs, the final over the last 2."""
    for rung in ladder.RUNGS:
        for agent in rung.agents:
            if finals.get(rung.name) is not None:
                write_cell(out, rung, agent, finals[rung.name])
    arms = rungs.ladder_arms(rungs.RUNGS, None, 0, 3, {}, str(out))
    return rungs.gap_line(arms, rungs.loaded_runs(arms), 2, stale)


CLOSING = {"image": (0.09, 0.1, 0.11), "ee": (0.5, 0.55, 0.6), "ee_obj": (0.97, 0.975, 0.98),
           "proprio": (0.985, 0.99, 0.995)}


@pytest.mark.parametrize("ee_obj, expected", [
    ((0.97, 0.975, 0.98), "baseline: image + ee_pos + obj_pos closes it (multimodal_baseline 0.975 against 0.990; "
                          "ee_obj − proprio -0.015 [-0.026, -0.004])"),
    # 0.04 below proprio, but three seeds this far apart leave the interval reaching to -0.152
    ((0.9, 0.96, 0.99), "baseline: no rung below proprio closes it (ee_obj − proprio -0.040 [-0.152, 0.072]; 0.990 to "
                        "reach)"),
])
def test_a_rung_closes_the_gap_when_welchs_interval_of_its_finals_less_the_tops_reaches_no_lower_than_close(
        ee_obj, expected, tmp_path):
    line = gap(tmp_path, {**CLOSING, "ee_obj": ee_obj})
    assert line.startswith(
        "Closes the gap (there is one when every proprio seed is above the floor and the image rung's final is more "
        "than 0.05 below the proprio rung's; a rung closes it when Welch's 95 % interval of its per-seed finals less "
        "the proprio rung's lies at or above −0.05): ")
    assert expected in line


def test_seeds_that_do_not_vary_close_the_gap_on_their_difference_alone(tmp_path):
    line = gap(tmp_path, {**CLOSING, "ee_obj": (1.0, 1.0, 1.0), "proprio": (1.0, 1.0, 1.0)})
    assert "bidal: image + ee_pos + obj_pos closes it (multimodal_bidal 1.000 against 1.000; ee_obj − proprio " \
           "+0.000 [0.000, 0.000])" in line


@pytest.mark.parametrize("epochs", [None, 2])  # no run, or one short of its 3 epochs
def test_a_rung_that_would_close_the_gap_above_an_unfinished_one_leaves_it_not_measured(epochs, tmp_path):
    if epochs:
        for agent in ladder.RUNGS[1].agents:
            write_cell(tmp_path, ladder.RUNGS[1], agent, CLOSING["ee"], epochs)
    line = gap(tmp_path, {**CLOSING, "ee": None})
    assert "closes it (" not in line
    assert ("baseline: not measured (ee not finished); the first finished rung to close it is ee_obj "
            "(multimodal_baseline 0.975 against 0.990; ee_obj − proprio -0.015 [-0.026, -0.004])") in line


def test_a_stale_cell_leaves_the_gap_not_measured_as_an_unfinished_one_does(tmp_path):
    line = gap(tmp_path, CLOSING, stale=["ee_obj/multimodal_bidal", "proprio/multimodal_baseline"])
    assert "baseline: not measured (proprio/multimodal_baseline, the level to reach, is stale)" in line
    assert ("bidal: not measured (ee_obj stale); no finished rung below proprio closes it (ee − proprio -0.440 "
            "[-0.563, -0.317]; 0.990 to reach).") in line


def test_the_tables_pass_the_stale_runs_to_the_gap_line(tmp_path, no_nicol):
    out = tmp_path / "out"
    for rung, finals in zip(ladder.RUNGS, ((0.09, 0.11), (0.5, 0.6), (0.975, 0.98), (0.985, 0.99))):
        for agent in rung.agents:  # bidal's ee_obj closes the gap, but on other physics
            write_cell(out, rung, agent, finals, physics="fedcba9876543210" if agent == "multimodal_bidal"
                       and rung.name == "ee_obj" else TODAY)
    assert ladder.main(["--report", *EXPERIMENT, "--out", str(out)]) == 0
    table = (out / "table.md").read_text()
    assert "baseline: image + ee_pos + obj_pos closes it (multimodal_baseline 0.978 against 0.988; ee_obj − " in table
    assert "bidal: not measured (ee_obj stale); no finished rung below proprio closes it (ee − proprio" in table
    assert "† stale: ee_obj/multimodal_bidal, runs not recorded on today's physics" in table


@pytest.mark.parametrize("finals, expected", [
    # proprio does not learn: 0.04 of 2 × 128 episodes is not clearly above nicol_slide's floor, 0.031
    ({"image": (0.0,) * 3, "ee": (0.0,) * 3, "ee_obj": (0.0,) * 3, "proprio": (0.04,) * 3},
     "no gap to close (multimodal_baseline 0.040, 0/3 seeds above its floor)"),
    ({**CLOSING, "image": (0.94, 0.95, 0.96)}, "no gap to close (visual_baseline 0.950, multimodal_baseline 0.990)"),
])
def test_no_rung_closes_a_gap_that_is_not_there(finals, expected, tmp_path):
    line = gap(tmp_path, finals)
    assert f"baseline: {expected}" in line and "closes it (" not in line


def test_runs_resumed_with_an_empty_buffer_are_named_below_both_tables(tmp_path, no_nicol):
    out = tmp_path / "out"
    fake_ladder(out)
    config = out / "image" / "visual_bidal" / "config.json"
    config.write_text(json.dumps({**json.loads(config.read_text()), "fresh_buffer_epochs": [2]}))
    assert ladder.main(["--report", *EXPERIMENT, "--out", str(out)]) == 0
    note = ("Resumed on another machine with an empty replay buffer (`--resume --fresh-buffer`, a deviation from an "
            "uninterrupted run: the next epochs learn from fresh episodes only): image/visual_bidal after epoch 2.")
    assert note in (out / "table.md").read_text()
    assert rungs.docs_table(str(out)).endswith(f"\n\n{note}")


def write_digest(run_dir, step, text):
    """The digest item of the run's checkpoint `step`, as Orbax writes it."""
    path = os.path.join(run_dir, "checkpoints", str(step), "digest")
    os.makedirs(path, exist_ok=True)
    with open(os.path.join(path, "metadata"), "w") as f:
        f.write(text)


def test_a_cell_retrained_to_the_probed_step_is_probed_again(tmp_path):
    arms = rungs.ladder_arms(rungs.RUNGS[:1], 2, 0, 3, {}, str(tmp_path))
    for arm in arms:
        write_fake_run(arm.run_dir, arm.given["env"], [(0.1, 0.1)] * 3, 3, agent=arm.given["agent"])
        write_digest(arm.run_dir, 3, '{"crc32": {"params": 1}}')
    probed = {arm.name: {"step": 3, "digest": ladder.checkpoint_digest(arm.run_dir, 3)} for arm in arms}
    assert ladder.to_probe(arms, probed) == []
    write_digest(arms[0].run_dir, 3, '{"crc32": {"params": 2}}')  # deleted and trained again to epoch 3
    assert ladder.to_probe(arms, probed) == arms[:1]
    # an entry written before probes kept the digest: its cell is probed again, the file is read as before
    assert ladder.to_probe(arms, {arm.name: {"step": 3} for arm in arms}) == arms


def test_the_checkpoint_digest_is_read_from_a_real_checkpoint(finished):
    run_dir, _ = finished
    found = [ladder.checkpoint_digest(run_dir, step) for step in checkpoint.steps(os.path.join(run_dir, "checkpoints"))]
    assert len(found) == 2 and all(len(digest) == 8 for digest in found) and found[0] != found[1]


def test_training_records_its_command_date_and_commit(tmp_path, no_nicol):
    out = tmp_path / "out"
    argv = [*EXPERIMENT, "--rungs", "image", "--out", str(out)]
    assert ladder.main(argv) == 0
    assert [call[1] for call in no_nicol if call[0] == "train"] == [
        os.path.join(out, "image", agent) for agent in ladder.VISUAL]
    [section] = json.loads((out / "figures.json").read_text())
    assert section["command"] == " ".join([ladder.PROG, *argv]) and section["date"] != ladder.NOT_RUN
    assert "figure" not in section  # the fake training wrote no epochs


def test_the_record_adds_each_new_command_once():
    first = ladder.section({"command": ladder.PROG, "date": ladder.NOT_RUN, "commit": ladder.NOT_RUN}, {}, "a")
    assert first["command"] == "a" and first["machine"] == ladder.NOT_RUN
    again = ladder.section(ladder.section(first, {}, "b"), {}, "a")
    assert again["command"] == "a; b" and again["date"] == first["date"] and again["commit"] == first["commit"]
    assert ladder.section(again, {}, None)["command"] == "a; b" and "gpu_sharing" not in again
    sharing = [{"runs": ["ladder/image/*"], "at_once": 2}]
    assert ladder.section({**again, "gpu_sharing": sharing}, {}, "c")["gpu_sharing"] == sharing


def test_an_axis_without_r2_reads_as_a_dash():
    assert rungs.axes([[0.5, None, 0.25], [0.7, None, 0.75]]) == "0.60, —, 0.50"


def test_a_seed_is_tested_against_the_floors_upper_bound():
    """0.037 over 10 epochs of 1,000 episodes is clearly above a floor estimated at 0.030 but not above its upper
    95 % bound, 0.040: the floor's Monte Carlo error does not count as learning."""
    run = {"env": "nicol_slide_ee", "agent": "multimodal_bidal", "config": {"train": {"eval_envs": 1000}},
           "success": np.full((10, 2), 0.037)}
    floors = {"nicol_slide": {"all": report.Floor(0.030, 0.010, 1.0)}}
    assert not protocol.seeds_above_floor(run, floors, 10).any()
    floors["nicol_slide"]["all"] = report.Floor(0.030, 0.0, 1.0)
    assert protocol.seeds_above_floor(run, floors, 10).all()
    assert protocol.above_floor(run, {}, 10) == ""
