"""Checks of a run's config, before anything is compiled or written.

`check(config, env_names=...)` raises `ConfigError` whose message is one line naming the
bad value (as its command-line option) and what is allowed, e.g. `--gamma 1.5: must be in
(0, 1)`. Each field's rule stands beside the field in `bidal_jax/config.py` (its
`metadata["rule"]`); the cross-field rules follow here (replay capacity, noise segments).
Pure: the facts it needs from outside (registered envs, an env's observation spec) are
arguments, so that this module imports neither the environments nor a device. How many
devices a run takes is `devices.device_layout`'s choice.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterable

from bidal_jax import noise
from bidal_jax.config import AGENTS, CONFIG_CLASSES, Config, ConfigError, Rule, TrainConfig, option


def rule(name: str) -> Rule:
    """The rule of the config field `name`, as its field declares it; KeyError for no such field."""
    for group in CONFIG_CLASSES.values():
        for f in dataclasses.fields(group):
            if f.name == name:
                return f.metadata["rule"]
    raise KeyError(name)


def check_field(name: str, value: Any) -> None:
    """Raise `ConfigError` when `value` breaks the rule of the config field `name`."""
    r = rule(name)
    bad_type = isinstance(value, bool) or not (
        isinstance(value, r.kind) or (r.kind is float and isinstance(value, int))
    )
    if bad_type:
        raise ConfigError(f"{option(name)} {value!r}: must be {r.what}, not a {type(value).__name__}")
    if r.kind is float and not math.isfinite(value):
        raise ConfigError(f"{option(name)} {value}: must be {r.what}, not {value}")
    if not r.allowed(value):
        raise ConfigError(f"{option(name)} {value}: must be {r.what}")


def _check_name(name: str, value: str, valid: Iterable[str]) -> None:
    valid = tuple(valid)
    if value not in valid:
        raise ConfigError(f"{option(name)} {value!r}: unknown {name}; valid: {', '.join(valid)}")


def check(config: Config, *, env_names: Iterable[str]) -> None:
    """Raise `ConfigError` for the first value the run cannot use."""
    for name in CONFIG_CLASSES:
        group = getattr(config, name)
        for f in dataclasses.fields(group):
            check_field(f.name, getattr(group, f.name))
    run, train = config.run, config.train
    _check_name("env", run.env, env_names)
    _check_name("agent", run.agent, AGENTS)
    if train.buffer_episodes % train.num_envs:
        raise ConfigError(
            f"--buffer-episodes {train.buffer_episodes}: must be a multiple of --num-envs {train.num_envs} "
            "(whole rollouts are written at once)"
        )
    if train.batch_size % train.sample_run:
        raise ConfigError(f"--sample-run {train.sample_run}: must divide --batch-size {train.batch_size} "
                          "(a batch is whole runs)")
    if train.obs_noise > 0 and not train.noise_segments.strip():
        raise ConfigError(f"--obs-noise {train.obs_noise}: needs --noise-segments (e.g. ee_pos,ee_rot,obj_pos)")


def check_env_support(train: TrainConfig, env: Any) -> None:
    """Raise `ConfigError` when `train` asks `env` for something it lacks (exploration starts,
    the proprio segments that get noise, a noisy achieved goal, runs longer than its episodes)."""
    unknown = [n for n in noise.parse_segments(train.noise_segments) if n not in env.observation_spec.segment_names]
    if unknown:
        raise ConfigError(
            f"{option('noise_segments')} {train.noise_segments}: env {env.name} has no segment {unknown[0]!r}; "
            f"its segments are {', '.join(env.observation_spec.segment_names)}"
        )
    try:
        noise.noise_map(env.observation_spec, noise.parse_segments(train.noise_segments), train.noise_variant)
    except ValueError as err:
        raise ConfigError(f"{option('noise_variant')} {train.noise_variant}: {err}") from err
    if train.sample_run > env.episode_length:
        raise ConfigError(f"{option('sample_run')} {train.sample_run}: env {env.name}'s episodes have "
                          f"{env.episode_length} steps; must be at most that")
    if train.exploration_starts > 0 and not env.has_exploration_start:
        raise ConfigError(
            f"{option('exploration_starts')} {train.exploration_starts}: env {env.name} has no exploration start; "
            "must be 0"
        )
