"""What a run asks of its env is checked before anything is built (bidal_jax/run/validate.py); the
command-line refusals of every field's rule are tests/bidal_jax/run/test_preflight.py's."""

import dataclasses

import pytest

import envs_mjx
from bidal_jax.config import ConfigError, TrainConfig
from bidal_jax.run import validate


def test_exploration_starts_need_an_env_that_has_them():
    env = envs_mjx.make("planar_reach", render=False)
    with pytest.raises(ConfigError, match="--exploration-starts 0.5: env planar_reach has no exploration start"):
        validate.check_env_support(dataclasses.replace(TrainConfig(), exploration_starts=0.5), env)


def test_noise_segments_must_be_the_envs():
    env = envs_mjx.make("planar_reach", render=False)
    with pytest.raises(ConfigError, match="env planar_reach has no segment 'ee_pos'; its segments are q, qdot"):
        validate.check_env_support(TrainConfig(noise_segments="ee_pos"), env)


def test_a_field_is_checked_by_the_rule_beside_it():
    with pytest.raises(ConfigError, match=r"--gamma 1.5: must be in \(0, 1\)"):
        validate.check_field("gamma", 1.5)
    with pytest.raises(ConfigError, match="--num-envs True: must be a positive integer, not a bool"):
        validate.check_field("num_envs", True)
    validate.check_field("conv_strides", "2,2,1,1")
