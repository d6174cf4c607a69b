"""The encoder probe (experiments/probes/encoder.py): ridge regression that recovers a linear target and not noise,
splits by episode, and probes a tiny randomly initialised encoder on synthetic frames."""

import types

import jax
import numpy as np
import pytest

from bidal_jax import normalizer
from envs_mjx.base import ObservationSpec
from envs_mjx.nicol import PROPRIO_SEGMENTS
from experiments.cli import resolve
from experiments.probes import encoder

TINY = {"conv_channels": 2, "vision_features": 4, "latent_size": 3, "conv_impl": "patch", "vision_dtype": "float32"}
SPEC = ObservationSpec(proprio_segments=PROPRIO_SEGMENTS, goal_size=3)
EPISODES, STEPS = 10, 4


@pytest.fixture(scope="module")
def frames():
    """Synthetic frames of `EPISODES` episodes of `STEPS` frames: random images and proprio of nicol_slide's layout."""
    rng = np.random.default_rng(0)
    n = EPISODES * STEPS
    return encoder.Frames(rng.integers(0, 256, (n, 42, 42, 1), dtype=np.uint8),
                          rng.normal(size=(n, SPEC.proprio_size)).astype(np.float32), np.arange(n) // STEPS, SPEC)


def test_the_split_holds_out_whole_episodes():
    episode = np.repeat(np.arange(10), 3)
    train, test = encoder.split(episode)
    assert set(episode[test]) == {8, 9} and not set(episode[train]) & set(episode[test])
    with pytest.raises(ValueError, match="1 episode"):
        encoder.split(np.zeros(5, int))


def test_ridge_recovers_a_linearly_encoded_target_and_not_noise():
    rng = np.random.default_rng(1)
    n = 400
    target = rng.normal(size=(n, 3))
    mixed = np.concatenate([target @ rng.normal(size=(3, 3)), rng.normal(size=(n, 5))], axis=1)  # target, mixed in
    episode = np.arange(n) // 10
    found = encoder.ridge_probe(mixed, target, episode)
    assert np.all(found["r2"] > 0.999) and np.all(found["rmse"] < 0.05)
    noise = encoder.ridge_probe(rng.normal(size=(n, 8)), target, episode)
    assert np.all(noise["r2"] < 0.2) and noise["alpha"] in encoder.ALPHAS


def test_r2_is_undefined_along_an_axis_that_hardly_varies():
    y = np.stack([np.linspace(0.0, 1.0, 50), np.full(50, 0.825) + 1e-4 * np.sin(np.arange(50))], axis=1)
    found = encoder.r2(y + 0.01, y)
    assert found[0] == pytest.approx(1.0 - 1e-4 / y[:, 0].var()) and np.isnan(found[1])


@pytest.mark.parametrize("agent, segments", [("visual_bidal", ()), ("multimodal_baseline", ("ee_pos",))])
def test_a_tiny_random_encoder_gives_finite_figures_per_seed_and_axis(frames, agent, segments):
    config = resolve({"env": "nicol_slide", "agent": agent, **TINY})
    spec = SPEC.without(tuple(n for n in SPEC.segment_names if n not in segments)) if segments else SPEC
    env = types.SimpleNamespace(observation_spec=spec, action_size=7)
    norms = jax.tree.map(lambda x: np.stack([x, x]), normalizer.init(spec.proprio_size))  # 2 seeds
    like = encoder.Encoding(config, None, norms)
    random = encoder.random_encoder(like, env)
    assert random.seeds == 2
    found = encoder.features(random, frames, spec.segment_names)
    assert found["phi"].shape == (2, len(frames.image), 3) and found["image"].shape == (2, len(frames.image), 4)
    assert not np.allclose(found["phi"][0], found["phi"][1])  # each seed its own key
    result = encoder.probe(random, frames, spec.segment_names)
    for features in encoder.FEATURES:
        for target in encoder.TARGETS:
            r2, rmse = (np.array(result[features][target][k]) for k in ("r2", "rmse_cm"))
            assert r2.shape == rmse.shape == (2, 3) and np.isfinite(r2).all() and (rmse > 0).all()


def test_a_run_without_an_encoder_is_refused(finished):
    run_dir, _ = finished  # proprio_baseline
    with pytest.raises(ValueError, match="proprio_baseline has no encoder to probe"):
        encoder.load_encoder(run_dir)
