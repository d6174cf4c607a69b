"""experiments.bench.sweep: variants as config overrides and physics options; the report's thresholds."""

import json

import pytest

from experiments.bench import sweep


def test_variants_are_typed_overrides_and_physics_options():
    assert sweep.parse_variant("preset") == ({}, {}, {})
    overrides, network, options = sweep.parse_variant(
        "updates_per_cycle=320,actor_lr=0.0005,net.hidden_layers=3,opt.iterations=5")
    assert overrides == {"updates_per_cycle": 320, "actor_lr": 0.0005} and type(overrides["updates_per_cycle"]) is int
    assert network == {"hidden_layers": 3} and type(network["hidden_layers"]) is int
    assert options == {"iterations": "5"}
    with pytest.raises(SystemExit, match="not a TrainConfig field"):
        sweep.parse_variant("updates=3")
    with pytest.raises(SystemExit, match="net.NAME of a NetworkConfig field"):
        sweep.parse_variant("net.width=3")


def test_report_gives_the_first_epoch_at_each_threshold(tmp_path):
    path = tmp_path / "cell.jsonl"
    rows = [{"variant": "preset", "epoch": e, "eval_success": s, "env_steps_per_seed": 1000 * e,
             "variant_seconds": 10.0 * e} for e, s in enumerate((0.1, 0.55, 0.85, 0.6), start=1)]
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    table = sweep.report([str(path)])
    assert "| 20 / 2,000 | 30 / 3,000 | — |" in table


def test_until_stops_a_variant_at_its_threshold(tmp_path, monkeypatch):
    import types

    import numpy as np

    successes = iter((0.2, 0.6, 0.95, 0.97))

    def fake_program(*args, **kwargs):
        state = types.SimpleNamespace(env_steps=np.zeros(2, int), updates=np.zeros(2, int))
        env = types.SimpleNamespace(physics_id="0123456789abcdef", backend="jax")
        return lambda keys: state, lambda s: (s, {"eval_success": np.full(2, next(successes))}), None, env

    monkeypatch.setattr(sweep, "seeded_program", fake_program)
    out = tmp_path / "cell.jsonl"
    sweep.main(["--env", "planar_reach", "--seeds", "2", "--epochs", "4", "--until", "0.9", "--out", str(out)])
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert [row["epoch"] for row in rows] == [1, 2, 3]
    assert {(row["physics"], row["engine"]) for row in rows} == {("0123456789abcdef", "jax")}
    with pytest.raises(SystemExit, match=r"--until 1.5: a success rate in \[0, 1\]"):
        sweep.main(["--until", "1.5", "--out", str(out)])


def test_a_variant_the_run_would_refuse_stops_the_sweep_before_any_trains(tmp_path, monkeypatch):
    monkeypatch.setattr(sweep, "seeded_program", lambda *a, **k: pytest.fail("a variant trained"))
    out = tmp_path / "cell.jsonl"
    with pytest.raises(SystemExit, match=r"error: --variant num_envs=3000,cycles_per_epoch=1: --buffer-episodes \d+: "
                                         r"must be a multiple of --num-envs 3000"):
        sweep.main(["--env", "nicol_slide", "--variant", "preset", "--variant", "num_envs=3000,cycles_per_epoch=1",
                    "--out", str(out)])
    assert not out.exists()
