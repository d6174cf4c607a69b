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
from experiments import report, stats
from experiments.paper import claims, protocol
from tests.conftest import TODAY, write_fake_run

EPOCHS = 100  # longer than every budget of a noise or transfer run, which the fake runs must reach to be measured
# every task's floor 0.1 (0.01 over nicol_lift's air goals, half its goals): above it the BidAL agents learn, the
# visual baseline at 0.03-0.07 does not
FLOORS = {task: {"all": report.Floor(0.1, 0.001, 1.0)} for task in protocol.paper_tasks()}
FLOORS["nicol_lift"] = {**FLOORS["nicol_lift"], "air": report.Floor(0.01, 0.001, 0.5)}


def write_floors(folder) -> str:
    """FLOORS as `python -m experiments.probes.floors` stores them, in `folder`; returns it."""
    os.makedirs(folder, exist_ok=True)
    stored = {task: {name: {"value": f.value, "half_width": f.half_width, "resets": int(1000 * f.share),
                            "rollouts": 10} for name, f in subsets.items()} for task, subsets in FLOORS.items()}
    with open(os.path.join(folder, "figures.json"), "w") as f:
        json.dump([{"floors": stored}], f)
    return str(folder)


@pytest.fixture(autouse=True)
def todays_physics(monkeypatch):
    """Every env steps the physics `TODAY` (no env is built)."""
    monkeypatch.setattr(envs_mjx, "make", lambda name, **kw: types.SimpleNamespace(physics_id=TODAY))


@pytest.fixture
def fake_run():
    """`write_fake_run` of runs made on today's physics."""
    return functools.partial(write_fake_run, physics=[TODAY])


def rows(levels, epochs=EPOCHS, wobble=0.0):
    """Per epoch, each seed's success: seed i at levels[i], ± `wobble` on alternate epochs, the pattern mirrored
    over the last 15 epochs so that a line fitted through the last 30 has no slope."""
    sign = [(-1) ** e * (-1 if e >= epochs - 15 else 1) for e in range(epochs)]
    return [[level + wobble * sign[e] for level in levels] for e in range(epochs)]


def rising(rate, seeds=5, epochs=EPOCHS):
    """Seed i's success min(1, rate·(epoch + 1) + 0.01·i): reaches 0.5 near epoch 0.5 / rate."""
    return [[min(1.0, rate * (e + 1) + 0.01 * i) for i in range(seeds)] for e in range(epochs)]


def write_transfer(fake_run, out, transfer_rate, scratch_rate, scratch_epochs=EPOCHS):
    fake_run(str(out / "transfer"), "nicol_lift_reduced", rising(transfer_rate), None)
    if scratch_epochs:
        fake_run(str(out / "scratch"), "nicol_lift_reduced", rising(scratch_rate, epochs=scratch_epochs), None)


def test_verdict_rule():
    F, A, U, C = claims.FAVOURS, claims.AGAINST, claims.UNCLEAR, claims.AT_CEILING
    assert claims.verdict([F, F]) == claims.verdict([F, C]) == "reproduced"  # at the ceiling: does not decide
    assert claims.verdict([F, A]) == claims.verdict([U]) == "not reproduced"
    assert claims.verdict([A, U]) == "reversed"
    assert claims.verdict([C, C]).startswith("not reproduced (at the ceiling")
    up = stats.Difference(0.1, 0.05, 0.15, 0.01)
    assert claims.check(up, 0.01, True) == F and claims.check(up, 0.01, False) == A
    assert claims.check(up, 0.2, True) == U and claims.check(up, 0.01, True, ceiling=True) == C


def test_holm_decides_a_claim_of_several_checks():
    weak, strong = stats.Difference(0.1, 0.0, 0.2, 0.04), stats.Difference(0.1, 0.05, 0.15, 0.03)
    # Holm: 2 × 0.03 = 0.06, then max(0.06, 0.04): neither decides
    assert claims.holm_checks([weak, strong], True, [False, False]) == [claims.UNCLEAR, claims.UNCLEAR]
    assert claims.holm_checks([weak], True, [False]) == [claims.FAVOURS]  # alone, p 0.04 < 0.05
    # a check at the ceiling leaves the correction to the others
    assert claims.holm_checks([weak, strong], True, [False, True]) == [claims.FAVOURS, claims.AT_CEILING]


@pytest.mark.parametrize("transfer_rate, scratch_rate, expected", [
    (0.1, 0.02, "reproduced"),  # transfer reaches 0.5 at epoch ~5, scratch at ~25
    (0.02, 0.1, "reversed"),
    (0.05, 0.05, "not reproduced"),  # the same curves: the interval straddles 0
])
def test_transfer_verdicts(tmp_path, fake_run, transfer_rate, scratch_rate, expected):
    write_transfer(fake_run, tmp_path, transfer_rate, scratch_rate)
    (row,) = claims.transfer_claims(str(tmp_path), set(), FLOORS)
    assert row.verdict == expected and "(primary)" in row.ours and "floor 0.100" in row.ours


def test_transfer_not_measured_when_an_arm_is_missing_or_short_and_stale_tasks_qualify(tmp_path, fake_run):
    write_transfer(fake_run, tmp_path / "missing", 0.1, 0.02, scratch_epochs=0)
    assert claims.transfer_claims(str(tmp_path / "missing"), set(), FLOORS)[0].verdict == \
        "not measured: scratch missing"
    write_transfer(fake_run, tmp_path / "short", 0.1, 0.02, scratch_epochs=10)
    steps = claims.transfer_claims(str(tmp_path / "short"), {"nicol_lift_reduced"}, FLOORS)[0]
    assert steps.verdict == ("not measured: scratch short (10 of 25 epochs); measured on nicol_lift_reduced runs "
                             "not recorded on today's physics")
    assert "[" in steps.ours  # the figure and its interval are shown all the same
    write_transfer(fake_run, tmp_path / "stale", 0.1, 0.02)
    steps = claims.transfer_claims(str(tmp_path / "stale"), {"nicol_slide", "ur5_reach"}, FLOORS)[0]
    assert steps.verdict == "reproduced; measured on nicol_slide runs not recorded on today's physics"


def write_grid(fake_run, out):
    """The curves grid as the paper has it: BidAL agents learn, the visual baseline stays below the floors
    (`FLOORS`), multimodal BidAL leads everywhere by 0.07 and on lifting by 0.37, and rises twice as fast as the
    others (0.1 an epoch against 0.05, up to its level): a larger AUC, fewer env steps to 0.5 and 0.9."""
    for task in protocol.paper_tasks():
        lift = task == "nicol_lift"
        level = {"multimodal_bidal": 0.97, "multimodal_bidal_no_ri": 0.9, "visual_bidal": 0.7, "visual_baseline": 0.05,
                 "multimodal_baseline": 0.6 if lift else 0.9, "proprio_baseline": 0.5 if lift else 0.85}
        for agent in AGENTS:
            levels = [level[agent] + 0.01 * (i - 2) for i in range(5)]
            rate = 0.1 if agent == claims.OURS else 0.05
            success = [[min(x, rate * (e + 1)) for x in levels] for e in range(protocol.paper_epochs()[task])]
            fake_run(str(out / task / agent), task, success, None, agent)


def write_plain(fake_run, out, lifting, exploration_starts=0.0):
    """nicol_lift runs of the plain protocol in OUT/nicol_lift/<agent>, agent -> how many of 5 seeds lift (air-goal
    success 0.8; the others 0.1)."""
    for agent, k in lifting.items():
        run_dir = str(out / "nicol_lift" / agent)
        air = [[0.8] * k + [0.1] * (5 - k)] * protocol.paper_epochs()["nicol_lift"]
        fake_run(run_dir, "nicol_lift", air, None, agent, given={"exploration_starts": exploration_starts})
        with_air(run_dir, air)


def write_noise(fake_run, out, steady_agent="multimodal_bidal"):
    """Noise runs (3 κ × 5 runs a folder): `steady_agent` at 0.8 ± 0.01 an epoch, the others 0.6 ± 0.1."""
    for agent in protocol.NOISE_AGENTS:
        level, wobble = (0.8, 0.01) if agent == steady_agent else (0.6, 0.1)
        levels = [level + 0.01 * (i % 5 - 2) for i in range(15)]
        fake_run(str(out / agent), "nicol_slide", rows(levels, protocol.NOISE_EPOCHS, wobble), None, agent)


def test_the_command_writes_every_claim_reproduced_where_the_runs_agree_with_the_paper(tmp_path, fake_run, capsys):
    write_grid(fake_run, tmp_path / "curves")
    write_noise(fake_run, tmp_path / "noise")
    write_transfer(fake_run, tmp_path / "transfer", 0.1, 0.02)
    write_plain(fake_run, tmp_path / "plain", {claims.OURS: 5, "multimodal_baseline": 5, "proprio_baseline": 0})
    out = str(tmp_path / "claims.md")
    argv = ["--curves", str(tmp_path / "curves"), "--noise", str(tmp_path / "noise"), "--transfer",
            str(tmp_path / "transfer"), "--plain", str(tmp_path / "plain"), "--floors",
            write_floors(tmp_path / "floors"), "--out", out]
    assert claims.main(argv) == 0
    text = open(out).read()
    table = [line for line in text.splitlines() if line.startswith("| (")]
    assert len(table) == 12 and all(line.split(" | ")[3] == "reproduced" for line in table), table
    assert f"Regenerate: `python -m experiments.paper.claims {' '.join(argv)}`" in text
    assert "lowest: visual_bidal" in text and "0.700 [" in text and "(floor 0.100, 5 of 5 seeds above it)" in text
    assert claims.main([*argv, "--stale", "nicol_lift,bogus"]) == 2
    assert "unknown task 'bogus'" in capsys.readouterr().err


def test_noise_claims_reversed_when_a_baseline_is_the_steady_one_and_not_measured_when_short(tmp_path, fake_run):
    write_noise(fake_run, tmp_path / "reversed", steady_agent="multimodal_baseline")
    steadier, higher = claims.noise_claims(str(tmp_path / "reversed"), set(), FLOORS)
    # against the steady multimodal baseline: less steady and lower; against proprio: equal (unclear)
    assert steadier.verdict == higher.verdict == "reversed"
    short = tmp_path / "short"
    for agent in protocol.NOISE_AGENTS:
        fake_run(str(short / agent), "nicol_slide", rows([0.5] * 15, epochs=19), None, agent)
    assert claims.noise_claims(str(short), set(), FLOORS)[0].verdict.startswith(
        "not measured: multimodal_bidal short (19 of 45 epochs)")
    assert claims.noise_claims(str(tmp_path / "none"), set(), FLOORS)[0].verdict.startswith(
        "not measured: multimodal_bidal missing")
    per_kappa = tmp_path / "per-kappa"  # one κ's runs alone (`noise_robustness --kappas`), the other κ not yet
    for agent in protocol.NOISE_AGENTS:
        fake_run(str(per_kappa / protocol.kappa_dir(agent, 0.10)), "nicol_slide", rows([0.5] * 5, epochs=19), None,
                 agent)
    assert claims.noise_claims(str(per_kappa), set(), FLOORS)[0].verdict.startswith(
        "not measured: multimodal_bidal at κ 15% missing; multimodal_baseline at κ 15% missing; "
        "proprio_baseline at κ 15% missing (+3 more)")  # the 3 more: each κ 10 % folder is short, 19 of 100 epochs


def test_learning_claims_not_reproduced_when_the_visual_baseline_learns_a_task(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    shutil.rmtree(tmp_path / "planar_reach" / "visual_baseline")
    fake_run(str(tmp_path / "planar_reach" / "visual_baseline"), "planar_reach",
             rows([0.66] * 5, protocol.paper_epochs()["planar_reach"]), None, "visual_baseline")
    learn, visual, *_ = claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set(), FLOORS)
    assert learn.verdict == "reproduced" and visual.verdict == "not reproduced"
    assert visual.ours.startswith("highest: visual_baseline on planar_reach 0.660 [")
    assert "(floor 0.100, 5 of 5 seeds above it); 1 of 4 runs learned" in visual.ours
    # without the tasks' floors nothing can be called learned
    assert claims.learning_claims(claims.load_grid(str(tmp_path)), 10, set(), {})[0].verdict.startswith(
        "not measured: nicol_lift has no floor")


def test_noise_steadiness_is_not_measured_while_the_curves_climb(tmp_path, fake_run):
    for agent in protocol.NOISE_AGENTS:  # every run climbs 0.01 an epoch, ± 0.01 around the climb
        climb = [[0.3 + 0.01 * e + (0.01 if e % 2 else -0.01) + 0.001 * i for i in range(15)] for e in range(EPOCHS)]
        fake_run(str(tmp_path / agent), "nicol_slide", climb, None, agent)
    steadier, higher = claims.noise_claims(str(tmp_path), set(), FLOORS)
    assert steadier.verdict.startswith("not measured: curves still move over the window (multimodal_bidal at κ 10% "
                                       "(slope +0.0")
    assert not higher.verdict.startswith("not measured")
    curve = protocol.load_noise_curves(str(tmp_path))[0][0.10, claims.OURS]
    np.testing.assert_allclose(protocol.residual_spread(curve, 30), 0.01 * np.sqrt(30 / 28), rtol=0.05)


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
    text = claims.time_report(runs, old, str(tmp_path))
    # held alone: 3,600 s × 2 GPUs (the most its machines had) and 1,000 s × 1
    assert "physics: 2.3 h of GPU time held (curves 2.3 h (2 runs; processes 1.3 h), noise 0.0 h (0 runs; " in text
    assert "Summed process time, for comparison: 1.3 h (per machine, as config.json records it: 1 × GPU then 2 × " \
        "GPU: 1.0 h; not recorded: 0.3 h)" in text
    assert "runs older than that column (1) count their `wall_time`" in text
    assert text.endswith("Runs on other physics, not counted: 0.3 h of process time (1 run).")
    assert claims.time_report(runs, set(), str(tmp_path)).endswith(". No run is on other physics.")
    # the two runs shared one GPU, two at a time: they held it max(4,600 / 2, 3,600) s, on 2 GPUs
    (tmp_path / "curves" / "figures.json").write_text(json.dumps([{"gpu_sharing": [
        {"runs": ["curves/nicol_slide/*"], "at_once": 2}]}]))
    assert "physics: 2.0 h of GPU time held (curves 2.0 h (2 runs; processes 1.3 h)" in \
        claims.time_report(runs, old, str(tmp_path))


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
    assert "Machine time of the runs behind these claims" in text and f"--readme {readme}" in text
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


def learning(folder):
    """The rows of claim (a) by name: learn, visual, overall, lift, added multimodal_baseline, added λ = 0, seeds."""
    names = ("learn", "visual", "overall", "lift", "baseline", "reward", "seeds")
    return dict(zip(names, claims.learning_claims(claims.load_grid(str(folder)), 10, set(), FLOORS), strict=True))


def test_learning_speed_is_judged_by_auc_against_the_papers_baselines(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    rows = learning(tmp_path)
    assert all(rows[k].verdict == "reproduced" for k in ("overall", "lift", "baseline", "reward"))
    overall = rows["overall"]
    # the comparisons are the pre-registered ones: the paper's baselines, each with its Holm-adjusted p
    assert overall.claim.endswith("(against the paper's baselines, proprio_baseline and visual_baseline)")
    assert "vs proprio_baseline: AUC +" in overall.ours and "vs visual_baseline: AUC +" in overall.ours
    assert "Holm p = " in overall.ours and "reported, not deciding: final success" in overall.ours
    assert "multimodal_baseline" not in overall.ours and claims.ABLATION not in overall.ours
    assert "vs multimodal_baseline: AUC" in rows["baseline"].ours and "added arm" in rows["baseline"].claim
    assert f"vs {claims.ABLATION}: AUC" in rows["reward"].ours and "added arm" in rows["reward"].claim
    # the margin on lifting against the mean margin elsewhere: 0.35 against proprio_baseline, more than elsewhere
    assert rows["lift"].ours.startswith("nicol_lift margin − mean margin on planar_reach, ur5_reach, nicol_slide")


def test_a_secondary_measure_against_the_claim_does_not_reverse_it(tmp_path, fake_run):
    """multimodal_bidal's AUC equals the others' while it ends lower: final success is against, AUC unclear."""
    for task in protocol.paper_tasks():
        for agent in AGENTS:
            curve = [[0.5] * 5] * (protocol.paper_epochs()[task] // 2) + [[0.9 + 0.01 * i for i in range(5)]] * (
                protocol.paper_epochs()[task] - protocol.paper_epochs()[task] // 2)
            if agent == claims.OURS:  # the same mean over epochs, but reaching its level earlier and ending lower
                curve = [[0.7 + 0.01 * i for i in range(5)]] * len(curve)
            fake_run(str(tmp_path / task / agent), task, curve, None, agent)
    overall = learning(tmp_path)["overall"]
    assert "vs proprio_baseline: AUC " in overall.ours and "final success -0.2" in overall.ours
    assert overall.verdict == "not reproduced"


def test_a_measure_at_the_ceiling_does_not_decide(tmp_path, fake_run):
    for task in protocol.paper_tasks():
        for agent in AGENTS:
            level = 0.99 if agent != claims.VISUAL else 0.05
            fake_run(str(tmp_path / task / agent), task, rows([level + 0.001 * (i - 2) for i in range(5)],
                                                              protocol.paper_epochs()[task], 0.002), None, agent)
    rows_ = learning(tmp_path)
    assert "at the ceiling" in rows_["baseline"].ours
    assert rows_["baseline"].verdict == "not reproduced (at the ceiling: no check decides)"
    assert rows_["overall"].verdict == "reproduced"  # against visual_baseline alone: the ceiling apart


def test_a_missing_cell_leaves_the_claims_about_other_agents_measured(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    shutil.rmtree(tmp_path / "nicol_lift" / claims.ABLATION)
    rows_ = learning(tmp_path)
    assert [r.verdict for k, r in rows_.items() if k != "reward"] == ["reproduced"] * 6
    assert rows_["reward"].verdict == f"not measured: nicol_lift/{claims.ABLATION} missing"
    shutil.rmtree(tmp_path / "ur5_reach" / "visual_baseline")
    rows_ = learning(tmp_path)
    assert rows_["learn"].verdict == rows_["baseline"].verdict == "reproduced"  # their cells are all there
    missing = "not measured: ur5_reach/visual_baseline missing"
    assert rows_["visual"].verdict == rows_["overall"].verdict == rows_["lift"].verdict == rows_["seeds"].verdict \
        == missing


def test_a_lift_run_learns_on_air_goals_and_is_compared_on_the_measure_all_arms_have(tmp_path, fake_run):
    write_grid(fake_run, tmp_path)
    # multimodal_bidal slides but never lifts: 0.97 overall, 0.1 on air goals: above their do-nothing floor (0.01)
    # but not above what a policy that never lifts scores there (0.125)
    with_air(str(tmp_path / "nicol_lift" / claims.OURS), [[0.1] * 5] * protocol.paper_epochs()["nicol_lift"])
    rows_ = learning(tmp_path)
    assert rows_["learn"].verdict == "not reproduced"
    assert rows_["learn"].ours.startswith("lowest: multimodal_bidal on nicol_lift 0.100 [0.100, 0.100] (floor 0.125, "
                                          "0 of 5 seeds above it)")
    assert f"runs without that column ({', '.join(a for a in AGENTS if a != claims.OURS)})" in rows_["learn"].rule
    # compared with arms that lack the column, every arm is judged on overall success: 0.97, so 5 of 5 lift, against
    # the paper's baselines' 0.5 and 0.05 (below 0.75)
    assert f"{claims.OURS} 5/5 [" in rows_["seeds"].ours and rows_["seeds"].verdict == "reproduced"
    assert f"runs without that column ({', '.join(AGENTS)})" in rows_["overall"].rule
    # once every arm has it, every arm is judged on air goals: 0 of 5 lift, as many as the baselines
    for agent in AGENTS:
        if agent != claims.OURS:
            with_air(str(tmp_path / "nicol_lift" / agent), [[0.05] * 5] * protocol.paper_epochs()["nicol_lift"])
    rows_ = learning(tmp_path)
    assert f"{claims.OURS} 0/5 [" in rows_["seeds"].ours and rows_["seeds"].verdict == "not reproduced"
    assert "runs without that column" not in rows_["overall"].rule


@pytest.mark.parametrize("ours, other, expected", [
    (5, 0, [claims.FAVOURS]),  # p = 0.008
    (3, 0, [claims.UNCLEAR]),  # p = 0.167: too few seeds to tell
    (0, 5, [claims.AGAINST]),
])
def test_lifting_seeds_are_compared_by_fishers_exact_test(ours, other, expected):
    def final(k):
        return np.array([0.7] * k + [0.1] * (5 - k))

    checks, text = claims.seeds_lifting({claims.OURS: final(ours), "proprio_baseline": final(other)}, (),
                                        claims.OURS, ("proprio_baseline",))
    assert checks == expected and f"{claims.OURS} {ours}/5 [" in text and "Fisher vs proprio_baseline: p = " in text
    # judged on overall success (no air column), a seed lifts only at 0.75 or more
    assert claims.seeds_lifting({claims.OURS: final(5), "proprio_baseline": final(0)}, tuple(AGENTS), claims.OURS,
                                ("proprio_baseline",))[0] == [claims.UNCLEAR]


def test_plain_protocol_rows_are_not_measured_until_their_runs_exist(tmp_path, fake_run):
    ours, added = claims.plain_claims(str(tmp_path / "none"), 10, set())
    assert ours.verdict == (f"not measured: nicol_lift/{claims.OURS} ({tmp_path / 'none'}) missing; "
                            f"nicol_lift/proprio_baseline ({tmp_path / 'none'}) missing")
    assert "plain protocol" in ours.claim and "added arm" in added.claim
    write_plain(fake_run, tmp_path / "plain", {claims.OURS: 5, "multimodal_baseline": 2, "proprio_baseline": 0})
    ours, added = claims.plain_claims(str(tmp_path / "plain"), 10, set())
    assert ours.verdict == "reproduced" and added.verdict == "not reproduced"
    # held-start runs in the plain folder are not the plain protocol
    write_plain(fake_run, tmp_path / "held", {claims.OURS: 5, "proprio_baseline": 0}, exploration_starts=0.5)
    assert f"nicol_lift/{claims.OURS} ({tmp_path / 'held'}) is not of the plain protocol" in \
        claims.plain_claims(str(tmp_path / "held"), 10, set())[0].verdict


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


def test_a_run_short_of_its_planned_seeds_is_not_measured():
    run = {"epoch": np.arange(1, 31), "seeds": 2, "planned_seeds": 5}
    assert claims.gap("nicol_slide/proprio_baseline", run, 30) == "nicol_slide/proprio_baseline short (2 of 5 seeds)"
    assert claims.gap("x", {**run, "seeds": 5}, 30) is None


def test_transfer_arms_are_judged_over_the_same_epochs(tmp_path, fake_run):
    """Scratch trained 60 epochs where transfer trained its 25: both are judged over the first 25, where transfer
    climbs faster (over all 60, scratch's late epochs near 1 would read as a larger AUC: reversed)."""
    fake_run(str(tmp_path / "transfer"), "nicol_lift_reduced", rising(0.03, epochs=25), None)
    fake_run(str(tmp_path / "scratch"), "nicol_lift_reduced", rising(0.02, epochs=60), None, given={"epochs": 60})
    row = claims.transfer_claims(str(tmp_path), set(), FLOORS)[0]
    assert row.ours.startswith("AUC 0.410 − 0.280 = +0.130") and row.verdict == "reproduced"


def test_noise_success_at_the_ceiling_does_not_decide(tmp_path, fake_run):
    for agent in protocol.NOISE_AGENTS:
        levels = [0.99 + (0.005 if agent == claims.OURS else 0.0) + 0.001 * (i % 5 - 2) for i in range(15)]
        fake_run(str(tmp_path / agent), "nicol_slide", rows(levels, protocol.NOISE_EPOCHS, 0.001), None, agent)
    higher = claims.noise_claims(str(tmp_path), set(), FLOORS)[1]
    assert higher.verdict == "not reproduced (at the ceiling: no check decides)"
    assert "at the ceiling" in higher.ours and "Holm p" not in higher.ours
