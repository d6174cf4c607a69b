"""experiments.paper.claims on hand-written run folders (conftest's `write_fake_run`): each verdict
(reproduced, not reproduced, reversed, not measured) and the stale-task qualifier."""

import functools
import json
import shutil
import types

import pytest

import envs_mjx
from bidal_jax.config import AGENTS
from experiments.paper import claims, protocol
from tests.conftest import TODAY, write_fake_run

EPOCHS = 100  # the NICOL presets' budget, which the fake runs must reach to be measured


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
    write_transfer(fake_run, tmp_path / "short", 0.1, 0.02, scratch_epochs=30)
    steps = claims.transfer_claims(str(tmp_path / "short"), {"nicol_lift_reduced"})[0]
    assert steps.verdict == ("not measured: scratch short (30 of 100 epochs); measured on nicol_lift_reduced runs "
                             "not recorded on today's physics")
    assert "[" in steps.ours  # the figure and its interval are shown all the same
    write_transfer(fake_run, tmp_path / "stale", 0.1, 0.02)
    steps = claims.transfer_claims(str(tmp_path / "stale"), {"nicol_slide", "ur5_reach"})[0]
    assert steps.verdict == "reproduced; measured on nicol_slide runs not recorded on today's physics"


def write_grid(fake_run, out):
    """The curves grid as the paper has it: BidAL agents learn, the visual baseline does not, multimodal
    BidAL leads everywhere by 0.05 and on lifting by 0.3."""
    for task in protocol.TASKS:
        lift = task == "nicol_lift"
        level = {"multimodal_bidal": 0.9 if lift else 0.95, "visual_bidal": 0.7, "visual_baseline": 0.1,
                 "multimodal_baseline": 0.6 if lift else 0.9, "proprio_baseline": 0.5 if lift else 0.85}
        for agent in AGENTS:
            levels = [level[agent] + 0.01 * (i - 2) for i in range(5)]
            fake_run(str(out / task / agent), task, rows(levels, protocol.EPOCHS[task]), None, agent)


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
    assert len(table) == 8 and all(line.split(" | ")[3] == "reproduced" for line in table)
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
        "not measured: multimodal_bidal short (19 of 100 epochs)")
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
    fake_run(str(tmp_path / "planar_reach" / "visual_baseline"), "planar_reach", rows([0.66] * 5, 40), None,
             "visual_baseline")
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
    assert text.endswith("Runs on other physics, not counted: 0.3 h.")


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
