"""docs/results.md and docs/performance.md are what `python -m experiments.paper.results_docs` writes from
results/*/figures.json and the runs beside them; every folder of results/ has its sections; and the command renders,
checks and refuses as it says."""

import json
import os

import pytest

from experiments.paper import grid, results_docs
from tests.experiments.runs import RUN_A, write_run
from tests.helpers import REPO

RESULTS = os.path.join(REPO, "results")
SECTION = {"part": "Performance", "title": "An epoch", "about": "What it measures.", "command": "python -m x",
           "machine": "one machine", "date": "2026-01-01", "commit": "abc1234",
           "table": {"head": ["what", "s"], "rows": [["an epoch", "1.0"]]}, "note": "What it says."}


@pytest.mark.parametrize("page", list(results_docs.PAGES))
def test_each_page_is_what_the_command_writes(page):
    with open(os.path.join(REPO, page), encoding="utf-8") as f:
        committed = f.read()
    assert committed == results_docs.document(RESULTS, results_docs.FOLDERS, page), \
        f"{page} is not what `{results_docs.PROG}` writes: run it"
    assert committed.startswith(f"<!-- written by `{results_docs.PROG}`")
    assert len(committed.splitlines()) <= 400


def test_every_folder_of_results_has_its_sections_and_a_link():
    folders = {name for name in os.listdir(RESULTS) if os.path.isdir(os.path.join(RESULTS, name))}
    assert folders == set(results_docs.FOLDERS)
    text = ""
    for page in results_docs.PAGES:
        with open(os.path.join(REPO, page), encoding="utf-8") as f:
            text += f.read()
    assert [folder for folder in sorted(folders) if f"](../results/{folder}/)" not in text] == []


def write_figures(root, sections, folder="x"):
    os.makedirs(root / folder)
    (root / folder / "figures.json").write_text(json.dumps(sections))


def test_a_section_gives_its_record_beside_its_table_then_its_note_and_figure(tmp_path):
    write_figures(tmp_path, [{**SECTION, "figure": "curves.png"}])
    text = results_docs.document(str(tmp_path), ["x"], os.path.join("docs", "performance.md"))
    assert ("### An epoch\n\nWhat it measures.\n\nCommand: `python -m x`. Machine: one machine. Recorded 2026-01-01 "
            "at commit abc1234; data: [results/x/](../results/x/).\n\n| what | s |\n| --- | --- |\n| an epoch | 1.0 |"
            "\n\nWhat it says.\n\n![An epoch](../results/x/curves.png)\n") in text
    assert text.index("# Performance") < text.index("## Performance") < text.index("### An epoch")
    assert "### An epoch" not in results_docs.document(str(tmp_path), ["x"])  # a part on its own page alone


@pytest.mark.parametrize("change, message", [
    ({"commit": None}, "section 1 lacks commit"),
    ({"part": "Speed"}, "part 'Speed' is none of"),
    ({"table": "speed"}, "table 'speed' is none of"),
])
def test_a_bad_section_is_refused_naming_its_file(tmp_path, change, message):
    section = {k: v for k, v in {**SECTION, **change}.items() if v is not None}
    write_figures(tmp_path, [section])
    with pytest.raises(ValueError, match=message):
        results_docs.document(str(tmp_path), ["x"], os.path.join("docs", "performance.md"))


def test_check_fails_until_the_command_has_written_the_file(tmp_path, monkeypatch, capsys):
    write_figures(tmp_path / "results", [SECTION])
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "results.md").write_text("# Results\n\nan edit by hand\n")
    monkeypatch.setattr(results_docs, "REPO", str(tmp_path))
    monkeypatch.setattr(results_docs, "FOLDERS", ("x",))
    assert results_docs.main(["--check"]) == 1
    assert "is not what `python -m experiments.paper.results_docs` writes" in capsys.readouterr().err
    assert results_docs.main([]) == 0
    assert results_docs.main(["--check"]) == 0
    (tmp_path / "results" / "x" / "figures.json").write_text("[{")
    assert results_docs.main([]) == 2
    assert capsys.readouterr().err.startswith("error: ")


def _sweep(path, seeds_by_epoch):
    """A sweep's JSON lines (`experiments.bench.sweep --out`) with these per-seed eval successes, epoch by epoch."""
    with open(path, "w", encoding="utf-8") as f:
        for epoch, seeds in enumerate(seeds_by_epoch, 1):
            f.write(json.dumps({"epoch": epoch, "env_steps_per_seed": 1000 * epoch, "process_seconds": epoch,
                                "variant_seconds": epoch, "eval_success_seeds": seeds}) + "\n")


def test_a_lever_keeps_parity_unless_its_interval_lies_below_zero(tmp_path):
    """`levers` table: AUC per seed over the epochs both runs reached (the longer run's last epoch left out), the
    difference after − before with its interval, and "no" only where the whole interval is below 0."""
    _sweep(tmp_path / "before.jsonl", [[0.2, 0.3, 0.4], [0.6, 0.7, 0.8], [1.0, 1.0, 1.0]])
    _sweep(tmp_path / "same.jsonl", [[0.3, 0.2, 0.4], [0.7, 0.8, 0.6]])
    _sweep(tmp_path / "worse.jsonl", [[0.0, 0.1, 0.0], [0.1, 0.2, 0.1]])
    table = results_docs.lever_table(str(tmp_path), [["task", "same", "before.jsonl", "same.jsonl"],
                                                     ["task", "worse", "before.jsonl", "worse.jsonl"]])
    same, worse = table.splitlines()[2:]
    assert same.startswith("| task | same | 2 | 0.400, 0.500, 0.600 | 0.500, 0.500, 0.500 | +0.000 [")
    assert same.endswith("| yes |")
    assert "| -0.417 [" in worse and worse.endswith("| no |")


def test_the_strides_table_compares_each_row_with_its_tasks_first(tmp_path):
    """`strides` table: AUC per seed over the epochs every row of a task reached, the first row of a task its
    reference, the others its difference with an interval, and the seconds an epoch from `process_seconds`."""
    _sweep(tmp_path / "a.jsonl", [[0.2, 0.3, 0.4], [0.6, 0.7, 0.8], [1.0, 1.0, 1.0]])
    _sweep(tmp_path / "b.jsonl", [[0.0, 0.1, 0.0], [0.1, 0.2, 0.1]])
    _sweep(tmp_path / "c.jsonl", [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    table = results_docs.strides_table(str(tmp_path), [["task", "3,2,2,1", "a.jsonl"], ["task", "2,2,1,1", "b.jsonl"],
                                                       ["other", "3,2,2,1", "c.jsonl"]])
    a, b, c = table.splitlines()[2:]
    assert a.startswith("| task | 3,2,2,1 | 2 | 0.400, 0.500, 0.600 | 0.500 | reference |") and a.endswith("| 1.0 |")
    assert b.startswith("| task | 2,2,1,1 | 2 | 0.050, 0.150, 0.050 | 0.083 | -0.417 [")
    assert c.startswith("| other | 3,2,2,1 | 3 |") and "| reference |" in c


def test_the_curves_table_marks_an_agent_not_run_on_a_task_and_a_stale_run(tmp_path):
    """An agent run on one task but not on another gets "—" there; each task is headed by its budget; a run of
    today's config and physics is unmarked, one that is not (here: no physics recorded, 3 epochs) is marked."""
    for task in ("planar_reach", "ur5_reach"):
        (tmp_path / "curves" / task).mkdir(parents=True)
        write_run(tmp_path / "curves" / task / "proprio_baseline", "proprio_baseline", RUN_A, env=task)
    today = tmp_path / "curves" / "ur5_reach" / "multimodal_bidal"
    write_run(today, "multimodal_bidal", [([0.7] * 5, 8000 * epoch, epoch) for epoch in (1, 2, 3)])  # 5 seeds
    [arm] = grid.curve_arms(["ur5_reach"], ["multimodal_bidal"], 5, 0, None, {}, str(tmp_path / "curves"))
    physics = grid.physics_today(["ur5_reach"])["ur5_reach"]
    (today / "config.json").write_text(json.dumps({**arm.config.to_dict(), "physics": [physics]}))
    head, _, proprio, bidal, floor = results_docs.curves_table(str(tmp_path), "curves").splitlines()
    assert head == "| agent | planar_reach (100 epochs) | ur5_reach (150 epochs) |"
    assert proprio == "| proprio_baseline | 0.567 ± 0.100 (last 3) / 0.567† | 0.567 ± 0.100 (last 3) / 0.567† |"
    assert bidal == "| multimodal_bidal | — | 0.700 ± 0.000 (last 3) / 0.700 |"
    assert floor == "| floor: a policy that does nothing | not computed | not computed |"  # no tmp_path/floors


def test_the_roofline_table_takes_the_measured_row_of_its_variant(tmp_path):
    counted = {"parts": [{"part": "critic", "flops": {"f32": 494.7e6}, "bytes": 0}]}
    row = {"variant": "b", "device_kind": "NVIDIA H200", "ms": 0.05, "parts": [{"component": "critic", "ms": 0.02}]}
    (tmp_path / "floors.json").write_text(json.dumps(counted))
    (tmp_path / "measured.json").write_text(json.dumps([{**row, "variant": "a", "ms": 9.0}, row]))
    table = results_docs.roofline_table(str(tmp_path), ["floors.json", "measured.json", "b"])
    assert "| critic | 0.49 | — | 1.0 | 0.0 | 20 | 20× |" in table
    assert "| the update (wall time) |  |  | 1.0 | 0.0 | 50 | 50× |" in table
    with pytest.raises(ValueError, match="measured.json: no row of variant 'c'"):
        results_docs.roofline_table(str(tmp_path), ["floors.json", "measured.json", "c"])
