"""The λ sweep (experiments/paper/lambda_sweep.py) on hand-written run folders (`write_fake_run`), without training:
its runs, its table and the λ it names, and a bad --lambdas refused."""

from experiments.paper import lambda_sweep
from tests.conftest import TODAY, write_fake_run


def fake_sweep(out, levels):
    """A run per task and λ at `levels[λ]`, for 3 epochs of each task's seeds: a flat curve at that success."""
    for task, seeds in lambda_sweep.SEEDS.items():
        for lam, level in levels.items():
            write_fake_run(lambda_sweep.run_dir(str(out), task, lam), task, [[level] * seeds] * 3, None,
                           physics=[TODAY], given={"epochs": lambda_sweep.EPOCHS[task], "intrinsic_lambda": lam})


def test_the_table_gives_each_lambdas_auc_per_task_and_names_the_largest_mean(tmp_path, no_nicol, capsys):
    fake_sweep(tmp_path, {0.0: 0.4, 0.1: 0.6, 1.0: 0.2})
    assert lambda_sweep.main(["--lambdas", "0,0.1,0.3,1", "--out", str(tmp_path), "--report"]) == 0
    table = (tmp_path / "table.md").read_text()
    assert "| 0.1 | 0.600 [0.600, 0.600] | 0.600 [0.600, 0.600] | — | 0.600 |" in table
    assert "| 0.3 | — | — | — | — |" in table  # no run at λ 0.3
    assert "Largest mean AUC over the tasks: λ = 0.1; the default (`TrainConfig.intrinsic_lambda`) is 0.1." in table
    assert no_nicol == []


def test_the_runs_are_multimodal_bidal_at_each_lambda_on_both_tasks():
    arms = lambda_sweep.make_arms((0.0, 1.0), {"num_envs": 64}, "out")
    assert [a.name for a in arms] == ["nicol_slide/lambda-0", "nicol_slide/lambda-1", "nicol_lift/lambda-0",
                                      "nicol_lift/lambda-1"]
    assert {(a.config.run.agent, a.config.train.num_envs) for a in arms} == {("multimodal_bidal", 64)}
    assert [a.config.train.intrinsic_lambda for a in arms] == [0.0, 1.0, 0.0, 1.0]
    assert [a.config.train.exploration_starts for a in arms] == [0.0, 0.0, 0.5, 0.5]  # lifting's held starts


def test_a_bad_lambda_is_refused_in_one_line(tmp_path, capsys):
    assert lambda_sweep.main(["--lambdas", "0.1,-1", "--out", str(tmp_path), "--dry-run"]) == 2
    assert capsys.readouterr().err.strip() == (
        "error: --lambdas 0.1,-1: must be a comma list of numbers >= 0, e.g. 0,0.1,0.3,1")
