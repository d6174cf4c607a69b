"""experiments.evaluate (and bidal_jax.run.policy.load_noise) on a run trained with observation noise
(paper Eq. 9): κ and σ are restored from the checkpoint, the evaluation under them reproduces the run's
logged eval success, and `--clean` evaluates without noise, saying so."""

import csv
import dataclasses
import functools
import json
import os

import jax
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting, noise
from bidal_jax.run.policy import evaluate_seeds, load_noise, load_policy
from experiments import evaluate, run
from experiments.probes import noise_reliance
from tests.helpers import restored_state

SEEDS, EPOCHS, EVAL_ENVS, KAPPA = 2, 2, 16, 0.5
TINY = [
    "--env", "planar_reach", "--agent", "proprio_baseline", "--num-envs", "4", "--cycles-per-epoch", "2",
    "--updates-per-cycle", "2", "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", str(EVAL_ENVS),
    "--seeds", str(SEEDS), "--epochs", str(EPOCHS), "--obs-noise", str(KAPPA), "--noise-segments", "q", "--quiet",
]


@pytest.fixture(scope="module")
def noisy(tmp_path_factory):
    """A finished tiny run with observation noise on planar_reach's joint angles, and its last metrics row."""
    run_dir = str(tmp_path_factory.mktemp("noisy") / "run")
    assert run.main([*TINY, "--run-dir", run_dir]) == 0
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return run_dir, list(csv.DictReader(f))[-1]


def test_noise_state_is_restored_as_saved(noisy):
    run_dir, _ = noisy
    trained = load_policy(run_dir)
    restored = load_noise(run_dir, trained)
    state, _ = restored_state(run_dir)
    np.testing.assert_array_equal(np.asarray(restored.kappa), np.full(SEEDS, KAPPA, np.float32))
    np.testing.assert_array_equal(np.asarray(restored.sigma), np.asarray(state.noise.sigma))
    assert np.asarray(restored.sigma).shape == (SEEDS, 2) and (np.asarray(restored.sigma) > 0).all()
    config = trained.config
    clean = dataclasses.replace(trained, config=dataclasses.replace(
        config, train=dataclasses.replace(config.train, noise_segments="")))
    assert load_noise(run_dir, clean) is None


def test_noisy_evaluation_reproduces_the_logged_success_and_clean_says_so(noisy, tmp_path, capsys):
    run_dir, row = noisy
    path = str(tmp_path / "eval.json")
    assert evaluate.main(["--run-dir", run_dir, "--episodes", str(EVAL_ENVS), "--json", path, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert f"noisy as in training's evaluation, κ {KAPPA:g} on q" in out
    result = json.load(open(path))
    assert result["per_seed"] == [float(row[f"eval_success_seed{i}"]) for i in range(SEEDS)]
    assert evaluate.main(["--run-dir", run_dir, "--episodes", str(EVAL_ENVS), "--clean", "--quiet"]) == 0
    assert "observations: clean (--clean; the run trained with noise on q)" in capsys.readouterr().out


def test_the_restored_noise_changes_only_the_noised_features(noisy):
    run_dir, _ = noisy
    trained = load_policy(run_dir)
    seed_noise = jax.tree.map(lambda x: x[0], load_noise(run_dir, trained))
    env = envs_mjx.make("planar_reach", render=False)
    noise_map = noise.noise_map(env.observation_spec, ("q",))
    indices = noise_map.indices
    observe = functools.partial(noise.observe, seed_noise, noise_map)
    _, (seen, true) = acting.rollout(env, trained.policy(0), jax.random.PRNGKey(1), 4, observe=observe,
                                     record=lambda step: (step.obs["proprio"], step.state.obs["proprio"]))
    changed = np.asarray(seen != true).any(axis=(0, 1))
    assert changed[indices].all() and changed.sum() == len(indices)


def test_kappa_rescales_the_runs_noise_and_zero_is_clean(noisy, tmp_path, capsys):
    run_dir, _ = noisy
    results = {}
    for name, extra in (("clean", ["--clean"]), ("zero", ["--kappa", "0"]), ("loud", ["--kappa", "2.5"])):
        path = str(tmp_path / f"{name}.json")
        assert evaluate.main(["--run-dir", run_dir, "--episodes", str(EVAL_ENVS), "--json", path, "--quiet",
                              *extra]) == 0
        results[name] = json.load(open(path))
    out = capsys.readouterr().out
    assert f"noisy with κ 2.5 (--kappa; the run trained with κ {KAPPA:g}) on q" in out
    assert results["zero"]["per_seed"] == results["clean"]["per_seed"]
    restored = load_noise(run_dir, load_policy(run_dir))
    loud = evaluate.with_kappa(restored, 2.5)
    np.testing.assert_array_equal(np.asarray(loud.kappa), np.full(SEEDS, 2.5, np.float32))
    np.testing.assert_array_equal(np.asarray(loud.sigma), np.asarray(restored.sigma))


@pytest.mark.parametrize("extra, message", [
    (["--kappa", "-0.1"], "--kappa -0.1: must be a finite number >= 0"),
    (["--kappa", "nan"], "--kappa nan: must be a finite number >= 0"),
    (["--kappa", "0.1", "--clean"], "--clean and --kappa: give one"),
])
def test_bad_kappa_is_one_error_line(noisy, capsys, extra, message):
    run_dir, _ = noisy
    assert evaluate.main(["--run-dir", run_dir, "--quiet", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_kappa_needs_a_run_trained_with_noise():
    with pytest.raises(ValueError, match="trained without observation noise"):
        evaluate.with_kappa(None, 0.1)


def test_noise_reliance_noises_each_group_on_its_own_scale(noisy, tmp_path):
    run_dir, _ = noisy
    trained = load_policy(run_dir)
    env = envs_mjx.make("planar_reach", render=False)
    segments = env.observation_spec.proprio_segments
    sigma, clean = noise_reliance.clean_episodes(env, trained, trained.eval_key, EVAL_ENVS)
    assert sigma.shape == (SEEDS, env.observation_spec.proprio_size) and (sigma > 0).all()
    np.testing.assert_array_equal(clean, evaluate_seeds(env, trained, trained.eval_key, EVAL_ENVS))
    state = noise_reliance.noise_on(sigma, segments, ("qdot",), 2.0)
    qdot = noise.feature_indices(segments, ("qdot",))
    np.testing.assert_array_equal(np.asarray(state.sigma), sigma[:, qdot])
    np.testing.assert_array_equal(np.asarray(state.kappa), np.full(SEEDS, 2.0, np.float32))
    path = str(tmp_path / "table.md")
    assert noise_reliance.main(["--run-dir", run_dir, "--episodes", str(EVAL_ENVS), "--kappas", "0.5,4",
                                "--groups", "q;qdot", "--out", path]) == 0
    text = open(path).read()
    assert "| noised segments | κ 0.5 | κ 4 |" in text and "σ here / the run's σ on q: mean " in text
    assert [line.split(" |")[0] for line in text.splitlines() if line.startswith("| q")] == ["| q", "| qdot"]


@pytest.mark.parametrize("extra, message", [
    (["--groups", "q;;qdot"], "--groups 'q;;qdot': must be ';'-separated groups"),
    (["--groups", "q,hand"], "unknown proprio segment 'hand'"),
    (["--kappas", "0.1,0"], "--kappas '0.1,0': must be a comma list of finite numbers > 0"),
    (["--episodes", "0"], "--episodes 0: must be a positive integer"),
])
def test_noise_reliance_bad_input_is_one_error_line(noisy, capsys, extra, message):
    run_dir, _ = noisy
    assert noise_reliance.main(["--run-dir", run_dir, *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
