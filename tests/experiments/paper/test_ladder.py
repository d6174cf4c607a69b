"""The pixel agents' ladder (experiments/paper/ladder.py) without training (`no_nicol` and `write_fake_run` of
conftest.py): its cells and plan, bad input, the table with the gap line computed from the runs and the probe's
figures, and the record its figures.json keeps."""

import json
import os

import pytest

from experiments.paper import ladder, rungs
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
    assert ("Closes the gap (final within 0.05 of the proprio rung's): baseline: no rung below proprio closes it "
            "(0.970 to reach); bidal: image + ee_pos + obj_pos closes it (multimodal_bidal 0.950 against 0.960)."
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
    assert ("Linear probe of the visual agents' φ on held-out frames (2,000 of 200 scripted episodes), mean over "
            "seeds, R² per axis x, y, z (RMSE): visual_baseline obj_pos R² 0.50, 0.50, 0.50 (1.5, 1.5, 1.5 cm)") in docs
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
    assert ("bidal: not measured (ee, ee_obj not finished); no finished rung below proprio closes it (0.960 to "
            "reach).") in (out / "table.md").read_text()


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
