"""experiments.paper.claims on hand-written run folders (conftest's `write_fake_run`): each verdict
(reproduced, not reproduced, reversed, not measured) and the stale-task qualifier."""

import csv
import functools
import json
import os
import shutil
import types

import numpy as np
import pytest

import envs_mjx
from bidal_jax.config import AGENTS
from experiments import report
from experiments.paper import claims, protocol
from tests.conftest import TODAY, write_fake_run

EPOCHS = 100  # longer than every budget of a noise or transfer run, which the fake runs must reach to be measured


@pytest.fixture(autouse=True)
def todays_physics(monkeypatch):
    """Every env steps the physics `TODAY` (no env is built)."""
    monkeypatch.setattr(envs_mjx, "make", lambda name, **kw: types.SimpleNamespace(physics_id=TODAY))


@pytest.fixture
def fake_run():
    """`write_fake_run` of runs made on today's physics."""
    return functools.partial(write_fake_run, physics=[TODAY])


def rows(levels, epochs=EPOCHS, wobble=0.0):
    """Per epoch, each seed's success: seed i at levels[i], ± `wobble` on alternate epochs."""
    return [[level + (wobble if e % 2 else -wobble) for level in levels] for e in range(epochs)]


def rising(rate, seeds=5, epochs=EPOCHS):
    """Seed i's success min(1, rate·(epoch + 1) + 0.01·i): reaches 0.5 near epoch 0.5 / rate."""
    return [[min(1.0, rate * (e + 1) + 0.01 * i) for i in range(seeds)] for e in range(epochs)]


def write_transfer(fake_run, out, transfer_rate, scratch_rate, scratch_epochs=EPOCHS):
    fake_run(str(out / "transfer"), "nicol_lift_reduced", rising(transfer_rate), None)
    if scratch_epochs:
        fake_run(str(out / "scratch"), "nicol_lift_reduced", rising(scratch_rate, epochs=scratch_epochs), None)


def test_verdict_rule():
    F, A, U = claims.FAVOURS, claims.AGAINST, claims.UNCLEAR
    assert claims.verdict([F, F]) == "reproduced"
    assert claims.verdict([F, A]) == claims.verdict([U]) == "not reproduced"
    assert claims.verdict([A, U]) == "reversed"
    assert claims.compare(0.1, 0.2, True) == F and claims.compare(0.1, 0.2, False) == A
    assert claims.compare(-0.1, 0.2, True) == U


@pytest.mark.parametrize("transfer_rate, scratch_rate, expected", [
    (0.1, 0.02, "reproduced"),  # transfer reaches 0.5 at epoch ~5, scratch at ~25
    (0.02, 0.1, "reversed"),
    (0.05, 0.05, "not reproduced"),  # the same curves: the interval straddles 0
])
def test_transfer_verdicts(tmp_path, fake_run, transfer_rate, scratch_rate, expected):
    write_transfer(fake_run, tmp_path, transfer_rate, scratch_rate)
    steps, auc = claims.transfer_claims(str(tmp_path), set())
    assert steps.verdict == auc.verdict == expected


def test_transfer_not_measured_when_an_arm_is_missing_or_short_and_stale_tasks_qualify(tmp_path, fake_run):
    write_transfer(fake_run, tmp_path / "missing", 0.1, 0.02, scratch_epochs=0)
    assert claims.transfer_claims(str(tmp_path / "missing"), set())[0].verdict == "not measured: scratch missing"
    write_transfer(fake_run, tmp_path / "short", 0.1, 0.02, scratch_epochs=10)
    steps = claims.transfer_claims(str(tmp_path / "short"), {"nicol_lift_reduced"})[0]
    assert steps.verdict == ("not measured: scratch short (10 of 25 epochs); measured on nicol_lift_reduced runs "
                             "not recorded on today's physics")
    assert "[" in steps.ours  # the figure and its interval are shown all the same
    write_transfer(fake_run, tmp_path / "stale", 0.1, 0.02)
    steps = claims.transfer_claims(str(tmp_path / "stale"), {"nicol_slide", "ur5_reach"})[0]
    assert steps.verdict == "reproduced; measured on nicol_slide runs not recorded on today's physics"


def write_grid(fake_run, out):
    """The curves grid as the paper has it: BidAL agents learn, the visual baseline does not, multimodal
    BidAL leads everywhere by 0.07 and on lifting by 0.37, and rises twice as fast as the others (0.1 an epoch
    against 0.05, up to its level): a larger AUC, fewer env steps to 0.5 and 0.9."""
    for task in protocol.paper_tasks():
        lift = task == "nicol_lift"
        level = {"multimodal_bidal": 0.97, "multimodal_bidal_no_ri": 0.9, "visual_bidal": 0.7, "visual_baseline": 0.1,
                 "multimodal_baseline": 0.6 if lift else 0.9, "proprio_baseline": 0.5 if lift else 0.85}
        for agent in AGENTS:
            levels = [level[agent] + 0.01 * (i - 2) for i in range(5)]
            rate = 0.1 if agent == claims.OURS else 0.05
            success = [[min(x, rate * (e + 1)) for x in levels] for e in range(protocol.paper_epochs()[task])]
            fake_run(str(out / task / agent), task, success, None, agent)


def write_noise(fake_run, out, steady_agent="multimodal_bidal"):
    """Noise runs (3 κ × 5 runs a folder): `steady_agent` at 0.8 ± 0.01 an epoch, the others 0.6 ± 0.1."""
    for agent in protocol.NOISE_AGENTS:
        level, wobble = (0.8, 0.01) if agent == steady_agent else (0.6, 0.1)
        levels = [level + 0.01 * (i % 5 - 2) for i in range(15)]
        fake_run(str(out / agent), "nicol_slide", rows(levels, wobble=wobble), None, agent)


def test_the_command_writes_every_claim_reproduced_where_the_runs_agree_with_the_paper(tmp_path, fake_run, capsys):
    write_grid(fake_run, tmp_path / "curves")
    write_noise(fake_run, tmp_path / "noise")
    write_transfer(fake_run, tmp_path / "transfer", 0.1, 0.02)
    out = str(tmp_path / "claims.md")
    argv = ["--curves", str(tmp_path / "curves"), "--noise", str(tmp_path / "noise"), "--transfer",
            str(tmp_path / "transfer"), "--out", out]
    assert claims.main(argv) == 0
    text = open(out).read()
    table = [line for line in text.splitlines() if line.startswith("| (")]
    assert len(table) == 10 and all(line.split(" | ")[3] == "reproduced" for line in table)
    assert f"Regenerate: `python -m experiments.paper.claims {' '.join(argv)}`" in text
    assert "lowest: visual_bidal" in text and "0.700 [" in text
    assert claims.main([*argv, "--stale", "nicol_lift,bogus"]) == 2
    assert "unknown task 'bogus'" in capsys.readouterr().err


def test_noise_claims_reversed_when_a_baseline_is_the_steady_one_and_not_measured_when_short(tmp_path, fake_run):
    write_noise(fake_run, tmp_path / "reversed", steady_agent="multimodal_baseline")
    steadier, higher = claims.noise_claims(str(tmp_path / "reversed"), set())
    # against the steady multimodal baseline: less steady and lower; against proprio: equal (unclear)
    assert steadier.verdict == higher.verdict == "reversed"
    short = tmp_path / "short"
    for agent in protocol.NOISE_AGENTS:
        fake_run(str(short / agent), "nicol_slide", rows([0.5] * 15, epochs=19), None, agent)
    assert claims.noise_claims(str(short), set())[0].verdict.startswith(
        "not measured: multimodal_bidal short (19 of 45 epochs)")
    assert claims.noise_claims(str(tmp_path / "none"), set())[0].verdict.startswith(
        "not measured: multimodal_bidal missing")
    per_kappa = tmp_path / "per-kappa"  # one κ's runs alone (`noise_robustness --kappas`), the other κ not yet
    for agent in protocol.NOISE_AGENTS:
        fake_run(str(per_kappa / protocol.kappa_dir(agent, 0.10)), "nicol_slide", rows([0.5] * 5, epochs=19), None,
                 agent)
    assert claims.noise_claims(str(per_kappa), set())[0].verdict.startswith(
        "not measured: multimodal_bidal at κ 15% missing; multimodal_baseline at κ 15% missing; "
        "proprio_baseline at κ 15% missing (+3 more)")  # the 3 more: each κ 10 % folder is short, 19 of 100 epochs


def test_learning_claims_not_reproduced_when_the_visual_baseline_learns_a_task(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    shutil.rmtree(tmp_path / "planar_reach" / "visual_baseline")
    fake_run(str(tmp_path / "planar_reach" / "visual_baseline"), "planar_reach",
             rows([0.66] * 5, protocol.paper_epochs()["planar_reach"]), None, "visual_baseline")
    learn, visual, *_ = claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set())
    assert learn.verdict == "reproduced" and visual.verdict == "not reproduced"
    assert visual.ours.startswith("highest: visual_baseline on planar_reach 0.660")


def test_runs_on_other_or_unrecorded_physics_qualify_their_claims(tmp_path, fake_run):
    write_grid(fake_run, tmp_path / "curves")
    write_noise(fake_run, tmp_path / "noise")
    write_transfer(fake_run, tmp_path / "transfer", 0.1, 0.02)
    assert claims.per_task(claims.on_other_physics(claims.runs_below(str(tmp_path)))) == {}
    # the scratch arm was made before its physics was recorded, the transfer arm resumed after a model change
    shutil.rmtree(tmp_path / "transfer")
    write_fake_run(str(tmp_path / "transfer" / "scratch"), "nicol_lift_reduced", rising(0.02), None)
    fake_run(str(tmp_path / "transfer" / "transfer"), "nicol_lift_reduced", rising(0.1), None, physics=["old", TODAY])
    assert claims.per_task(claims.on_other_physics(claims.runs_below(str(tmp_path / "transfer")))) == {
        "nicol_lift_reduced": 2}
    out = str(tmp_path / "claims.md")
    assert claims.main(["--curves", str(tmp_path / "curves"), "--noise", str(tmp_path / "noise"), "--transfer",
                        str(tmp_path / "transfer"), "--out", out]) == 0
    text = open(out).read()
    assert "(c) " in text and "reproduced; measured on nicol_lift_reduced runs not recorded on today's physics" in text
    assert "Runs not recorded on today's physics" in text and "nicol_lift_reduced (2 runs)" in text
    # a folder's stale runs qualify its own claims only: (a) and (b) read other folders
    assert not any("today's physics" in line for line in text.splitlines() if line.startswith(("| (a)", "| (b)")))


def test_time_report_sums_the_runs_on_todays_physics_per_experiment_and_machine(tmp_path, fake_run):
    timed = tmp_path / "curves" / "nicol_slide" / "multimodal_bidal"
    fake_run(str(timed), "nicol_slide", rows([0.9] * 5), None, compile_seconds=2600.0)  # 1,000 + 2,600 s
    config = json.loads((timed / "config.json").read_text())
    (timed / "config.json").write_text(json.dumps({**config, "hardware": ["1 × GPU", "2 × GPU"]}))
    fake_run(str(tmp_path / "curves" / "nicol_slide" / "proprio_baseline"), "nicol_slide", rows([0.9] * 5), None,
             "proprio_baseline")  # 1,000 s, compiling not counted
    # physics not recorded: not counted
    write_fake_run(str(tmp_path / "transfer" / "scratch"), "nicol_lift_reduced", rising(0.02), None)
    (tmp_path / "noise").mkdir()
    names = ("curves", "noise", "transfer")
    runs = {name: claims.runs_below(str(tmp_path / name)) for name in names}
    old = {run["dir"] for run in claims.on_other_physics([run for found in runs.values() for run in found])}
    text = claims.time_report(runs, old)
    assert "physics: curves 1.3 h (2 runs), noise 0.0 h (0 runs), transfer 0.0 h (0 runs); in all 1.3 h" in text
    assert "(per machine, as config.json records it: 1 × GPU then 2 × GPU: 1.0 h; not recorded: 0.3 h)" in text
    assert "runs older than that column (1) count their `wall_time`" in text
    assert text.endswith("Runs on other physics, not counted: 0.3 h (1 run).")
    assert claims.time_report(runs, set()).endswith(". No run is on other physics.")


def test_readme_block_is_replaced_and_a_readme_without_one_is_refused(tmp_path, fake_run, capsys):
    write_transfer(fake_run, tmp_path / "transfer", 0.1, 0.02)
    readme, out = tmp_path / "README.md", str(tmp_path / "claims.md")
    readme.write_text(f"# title\n\n{claims.README_START}\nold table\n{claims.README_END}\n\nafter\n")
    argv = ["--curves", str(tmp_path / "curves"), "--noise", str(tmp_path / "noise"), "--transfer",
            str(tmp_path / "transfer"), "--out", out, "--readme", str(readme)]
    for _ in range(2):  # a second run replaces its own block
        assert claims.main(argv) == 0
    text = readme.read_text()
    assert text.startswith(f"# title\n\n{claims.README_START}\n| claim | ours (95 % interval) | paper | verdict |")
    assert text.endswith(f"{claims.README_END}\n\nafter\n") and "old table" not in text
    assert text.count(claims.README_START) == 1 and "| (c) reduced lift learns faster" in text
    assert "Time of the runs behind these claims" in text and f"--readme {readme}" in text
    readme.write_text("# no block\n")
    (tmp_path / "claims.md").unlink()
    assert claims.main(argv) == 2
    assert "no claims block to replace" in capsys.readouterr().err
    assert readme.read_text() == "# no block\n" and not (tmp_path / "claims.md").exists()


def with_air(run_dir, air):
    """Add per-seed `eval_success_air` columns to a fake run's metrics.csv: `air` per epoch, each seed's."""
    path = os.path.join(run_dir, "metrics.csv")
    with open(path, newline="") as f:
        table = list(csv.reader(f))
    table[0] += [f"{report.AIR}_seed{i}" for i in range(len(air[0]))]
    for line, values in zip(table[1:], air):
        line += [str(v) for v in values]
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows(table)


def test_learning_speed_enters_the_verdict_with_auc_and_steps_intervals(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    *_, overall, lift, seeds, reward = claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set())
    assert overall.verdict == lift.verdict == seeds.verdict == "reproduced"
    # multimodal_bidal reaches 0.5 at epoch 5 (500 env steps per seed), the others at epoch 10 (1,000)
    assert "env steps to 0.5 -500 [-500, -500] over multimodal_baseline" in lift.ours
    assert "AUC +" in overall.ours and "env steps to 0.9 (share of the budget) -" in overall.ours
    # the agent without the intrinsic reward is compared on its own row, never as the best other agent
    assert claims.ABLATION not in overall.ours + lift.ours and f"vs {claims.ABLATION}" not in seeds.ours
    assert reward.verdict == "reproduced" and f"over {claims.ABLATION}" in reward.ours
    # the same speed as the best other agent: the steps' intervals straddle 0, so the claim is not reproduced
    for task, epochs in protocol.paper_epochs().items():
        levels = [0.9 + 0.01 * (i - 2) for i in range(5)]
        fake_run(str(tmp_path / "slow" / task / claims.OURS), task,
                 [[min(x, 0.05 * (e + 1)) for x in levels] for e in range(epochs)], None, claims.OURS)
        for agent in set(AGENTS) - {claims.OURS}:
            shutil.copytree(tmp_path / task / agent, tmp_path / "slow" / task / agent)
    *_, overall, _, _, _ = claims.learning_claims(claims.load_grid(str(tmp_path / "slow")), 10, set())
    assert overall.verdict != "reproduced" and "env steps to 0.5 (share of the budget) +0.000 [0.000, 0.000]" \
        in overall.ours


def test_a_missing_cell_leaves_the_claims_about_other_agents_measured(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    shutil.rmtree(tmp_path / "nicol_lift" / claims.ABLATION)
    *paper, reward = claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set())
    assert [c.verdict for c in paper] == ["reproduced"] * 5
    assert reward.verdict == f"not measured: nicol_lift/{claims.ABLATION} missing"
    shutil.rmtree(tmp_path / "ur5_reach" / "visual_baseline")
    learn, visual, overall, lift, seeds, reward = claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set())
    assert learn.verdict == "reproduced"  # the BidAL agents' cells are all there
    missing = "not measured: ur5_reach/visual_baseline missing"
    assert visual.verdict == overall.verdict == lift.verdict == seeds.verdict == missing
    assert reward.verdict == f"not measured: nicol_lift/{claims.ABLATION} missing"


def test_lift_is_judged_on_air_goals_where_the_run_has_them(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    # multimodal_bidal slides but never lifts: 0.97 overall, 0.1 on air goals
    with_air(str(tmp_path / "nicol_lift" / claims.OURS), [[0.1] * 5] * protocol.paper_epochs()["nicol_lift"])
    learn, *_, seeds, _ = claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set())
    assert learn.verdict == "not reproduced" and "lowest: multimodal_bidal on nicol_lift 0.100" in learn.ours
    assert f"runs without that column ({', '.join(a for a in AGENTS if a != claims.OURS)})" in learn.rule
    assert f"{claims.OURS} 0/5 [" in seeds.ours and seeds.verdict == "not reproduced"  # 0/5 against 0/5: p = 1


@pytest.mark.parametrize("ours, other, expected", [
    (5, 0, "reproduced"),  # p = 0.008
    (3, 0, "not reproduced"),  # p = 0.167: too few seeds to tell
    (0, 5, "reversed"),
])
def test_lifting_seeds_are_compared_by_fishers_exact_test(ours, other, expected):
    def final(k):
        return np.array([0.7] * k + [0.1] * (5 - k))

    finals = {("nicol_lift", claims.OURS): final(ours), ("nicol_lift", "multimodal_baseline"): final(other),
              ("nicol_lift", "proprio_baseline"): final(0)}
    row = claims.lifting_claim(finals, (), [], set(), 10, ("lift", "paper"))
    assert row.verdict == expected
    assert f"{claims.OURS} {ours}/5 [" in row.ours and f"Fisher {claims.OURS} vs " in row.ours
    # judged on overall success (no air column), a seed lifts only at 0.75 or more
    assert claims.lifting_claim(finals, tuple(AGENTS), [], set(), 10, ("lift", "paper")).verdict == "not reproduced"


def test_the_previous_table_is_kept_under_its_heading(tmp_path, fake_run):
    write_transfer(fake_run, tmp_path / "transfer", 0.1, 0.02)
    old, out = tmp_path / "old.md", tmp_path / "claims.md"
    old.write_text("# The claims\n\n| claim |\n| --- |\n| (a) an old row |\n")
    argv = ["--curves", str(tmp_path / "curves"), "--noise", str(tmp_path / "noise"), "--transfer",
            str(tmp_path / "transfer"), "--out", str(out)]
    assert claims.main([*argv, "--previous", str(old)]) == 0
    for _ in range(2):  # written again without --previous: the section stays, once
        text = out.read_text()
        assert text.count(claims.PREVIOUS) == 1 and text.endswith("| (a) an old row |\n")
        assert text.index("| (c) reduced lift") < text.index(claims.PREVIOUS) < text.index("an old row")
        assert claims.main(argv) == 0
    assert claims.main([*argv, "--previous", str(tmp_path / "none.md")]) == 2
