"""Run reports (experiments/report.py) on hand-written run directories: reading a run, labels and
panels, thresholds, AUC, final success and the summary table."""

import numpy as np
import pytest

from experiments import report
from tests.experiments.runs import RUN_A, RUN_B, write_run


def test_load_run_gives_env_steps_per_seed(two_runs):
    run = report.load_run(two_runs[0])
    assert (run["env"], run["agent"], run["seeds"], run["name"]) == ("ur5_reach", "multimodal_bidal", 2, "a")
    np.testing.assert_allclose(run["env_steps"], [8000, 16000, 24000])  # 16000 summed over 2 seeds, ...
    np.testing.assert_allclose(run["success"], [[0.2, 0.4], [0.4, 0.6], [0.8, 1.0]])


def test_labels_by_basename_on_a_shared_agent_and_by_override(tmp_path):
    runs = [report.load_run(write_run(tmp_path / name, "multimodal_bidal", RUN_A)) for name in ("s1", "s2")]
    other = report.load_run(write_run(tmp_path / "slide", "multimodal_bidal", RUN_B, env="nicol_slide"))
    assert [(c.panel, c.label) for c in report.curves([*runs, other])] == [
        ("ur5_reach", "s1"), ("ur5_reach", "s2"), ("nicol_slide", "multimodal_bidal")]
    labels = {str(tmp_path / "s1") + "/": "scratch", str(tmp_path / "s2"): "transfer"}
    assert [c.label for c in report.curves(runs, labels=labels)] == ["scratch", "transfer"]
    assert [c.label for c in report.curves(runs, label_by=lambda r: r["name"].upper())] == ["S1", "S2"]
    with pytest.raises(ValueError, match="labelled 'same'"):
        report.curves(runs, labels={str(tmp_path / "s1"): "same", str(tmp_path / "s2"): "same"})


def test_label_by_a_config_value(tmp_path):
    runs = [report.load_run(write_run(tmp_path / f"k{i}", "multimodal_bidal", RUN_A, lam=lam))
            for i, lam in enumerate((0.05, 0.15))]
    assert [c.label for c in report.curves(runs, "train.intrinsic_lambda")] == [
        "intrinsic_lambda=0.05",
        "intrinsic_lambda=0.15",
    ]
    with pytest.raises(ValueError, match="train.kappa"):
        report.curves(runs, "train.kappa")


def test_threshold_and_auc_by_hand(two_runs):
    a, b = report.curves([report.load_run(d) for d in two_runs])
    # run a's seed means: 0.3, 0.5, 0.9
    assert report.time_to_threshold(a, 0.5) == report.Reached(epoch=2, env_steps=16000.0, wall_time=20.0)
    assert report.time_to_threshold(a, 0.95) is None
    assert report.time_to_threshold(b, 0.5) == report.Reached(epoch=1, env_steps=8000.0, wall_time=5.0)
    assert report.normalized_auc(a) == pytest.approx(1.7 / 3)
    assert report.normalized_auc(b) == pytest.approx(0.7)


def test_final_success_and_summary_table(two_runs):
    runs = [report.load_run(d) for d in two_runs]
    a, b = report.curves(runs)
    # last 2 epochs per seed, then across seeds: a (0.6, 0.8); b (0.5, 0.75, 0.85)
    np.testing.assert_allclose(report.final_success(a, 2), (0.7, 0.1, 2))
    np.testing.assert_allclose(report.final_success(b, 2), (0.7, np.sqrt(0.065 / 3), 2))
    # more epochs asked than run: all 3, a's seeds (1.4/3, 2/3)
    np.testing.assert_allclose(report.final_success(a, 5), (1.7 / 3, 0.1, 3))
    table = report.summary_table(runs, 5, threshold=0.8).splitlines()
    assert table[2] == "| ur5_reach | multimodal_bidal | 2 | 3 | 0.567 ± 0.100 (last 3) | 0.567 | 3, 24,000, 30 s |"
    assert table[3] == "| ur5_reach | proprio_baseline | 3 | 2 | 0.700 ± 0.147 (last 2) | 0.700 | 2, 16,000, 9 s |"


def test_absent_epochs_are_those_up_to_the_last_without_a_row_and_read_as_spans():
    assert report.absent_epochs(np.array([3.0, 4.0, 6.0, 7.0])) == [1, 2, 5]
    assert report.absent_epochs(np.arange(1.0, 5)) == []
    assert report.epoch_spans([1, 2, 5, 7, 8, 9]) == "1-2, 5, 7-9"
    assert report.epoch_spans([]) == ""
    assert report.absent_note({"a": [3.0, 4.0], "b": [1.0, 2.0], "c": [2.0, 4.0]}) == (
        "Epochs without a row in metrics.csv: a (1-2); c (1, 3); the final success averages the last rows there are.")
    assert report.absent_note({"b": [1.0, 2.0]}) == ""


def test_a_group_that_shared_a_gpu_is_counted_once_however_its_runs_are_split(tmp_path):
    """Three runs of an hour, three at a time on one GPU, one in the curves and two in transfer: they held it an
    hour, each a third; a subset's parts add up to its share, not to an hour per experiment."""
    runs = [{"dir": str(tmp_path / where), "config": {}, "wall_time": np.array([3600.0]),
             report.WITH_COMPILE: np.array([3600.0])} for where in ("curves/a", "transfer/b", "transfer/c")]
    shares = report.machine_shares(runs, str(tmp_path), [(("curves/a", "transfer/*"), 3)])
    assert shares == pytest.approx({run["dir"]: 1200.0 for run in runs})
    assert report.machine_time(runs, str(tmp_path), [(("curves/a", "transfer/*"), 3)]) == pytest.approx((3600.0,
                                                                                                         10800.0))
    alone = {**runs[0], "dir": str(tmp_path / "noise/d"), "config": {"hardware": ["1 × GPU", "2 × GPU"]}}
    assert report.machine_shares([alone], str(tmp_path), []) == {alone["dir"]: 7200.0}  # the largest machine


def test_a_cell_with_a_block_of_seeds_not_yet_trained_is_planned_whole(tmp_path):
    (tmp_path / "cell").mkdir()
    write_run(tmp_path / "cell" / report.block_name(0, 1), "proprio_baseline", RUN_A)  # 2 seeds
    (tmp_path / "cell" / report.block_name(2, 4)).mkdir()  # its block's folder made, no epochs yet
    run = report.load_run(str(tmp_path / "cell"))
    assert (run["seeds"], run["planned_seeds"]) == (2, 5)
