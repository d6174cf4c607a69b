"""Checks of a run's configs, before anything is compiled or written.

`check(run, train, net, env_names=...)` raises `ConfigError` whose
message is one line naming the bad value (as its command-line option) and what is
allowed, e.g. `--gamma 1.5: must be in (0, 1)`. Every config field has a rule in
`RULES`; the cross-field rules follow (replay capacity). Pure: the facts it needs from
outside (registered envs) are arguments, so that this module imports neither the
environments nor a device. How many devices a run takes is `train.device_layout`'s choice.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Iterable

from bidal_jax import noise
from bidal_jax.config import AGENTS, NetworkConfig, RunConfig, TrainConfig, parse_strides


class ConfigError(ValueError):
    """A config value that a run cannot use; the message is one line."""


def option(field: str) -> str:
    """The command-line option of a config field: `num_envs` -> `--num-envs`."""
    return "--" + field.replace("_", "-")


def _positive_int(v: Any) -> bool:
    return v >= 1


def _non_negative(v: Any) -> bool:
    return v >= 0


def _positive(v: Any) -> bool:
    return v > 0


def _probability(v: Any) -> bool:
    return 0 <= v <= 1


def _anything(v: Any) -> bool:
    return True


def _strides(v: str) -> bool:
    try:
        parse_strides(v)
    except ValueError:
        return False
    return True


def _name_list(v: str) -> bool:
    names = [name.strip() for name in v.split(",")]
    return all(name.isidentifier() for name in names) and len(set(names)) == len(names)


# field -> (type, predicate, what is allowed)
Rule = tuple[type, Callable[[Any], bool], str]
_POS_INT: Rule = (int, _positive_int, "a positive integer")
_POS: Rule = (float, _positive, "a positive number")
_NON_NEG: Rule = (float, _non_negative, "a number >= 0")
_PROB: Rule = (float, _probability, "a probability in [0, 1]")
RULES: dict[str, Rule] = {
    # run
    "env": (str, _anything, "an env name"),
    "agent": (str, _anything, "an agent name"),
    "seeds": _POS_INT,
    "seed": (int, lambda v: 0 <= v < 2**32, "an integer in [0, 2^32)"),
    "epochs": _POS_INT,
    "checkpoint_every": _POS_INT,
    "env_shards": _POS_INT,
    "run_dir": (str, _anything, "a path"),
    "target_success": _PROB,
    "init_from": (str, _anything, "RUN_DIR or RUN_DIR:CHECKPOINT"),
    "init_parts": (str, _name_list, "comma-separated network names without repeats, e.g. encoder,forward,inverse"),
    # train
    "num_envs": _POS_INT,
    "cycles_per_epoch": _POS_INT,
    "updates_per_cycle": _POS_INT,
    "batch_size": _POS_INT,
    "buffer_episodes": _POS_INT,
    "gamma": (float, lambda v: 0 < v < 1, "in (0, 1)"),
    "tau": (float, lambda v: 0 < v <= 1, "in (0, 1]"),
    "actor_lr": _POS,
    "critic_lr": _POS,
    "action_l2": _NON_NEG,
    "noise_eps": _NON_NEG,
    "random_eps": _PROB,
    "exploration_starts": _PROB,
    "obs_noise": _NON_NEG,
    "noise_segments": (str, _anything, "comma-separated proprio segment names"),
    "her_k": (int, _non_negative, "an integer >= 0"),
    "intrinsic_lambda": _NON_NEG,
    "forward_weight": _NON_NEG,
    "inverse_weight": _NON_NEG,
    "clip_obs": _POS,
    "eval_envs": _POS_INT,
    "grad_clip": _POS,
    # network
    "conv_channels": _POS_INT,
    "conv_strides": (str, _strides, "four comma-separated positive integers, e.g. 3,2,2,2"),
    "vision_features": _POS_INT,
    "proprio_features": _POS_INT,
    "latent_size": _POS_INT,
    "embed_size": _POS_INT,
    "hidden_size": _POS_INT,
    "hidden_layers": _POS_INT,
    "model_hidden_size": _POS_INT,
}


def check_field(name: str, value: Any) -> None:
    """Raise `ConfigError` when `value` breaks the rule of the config field `name` (`RULES`)."""
    if name not in RULES:  # a field newer than its rule (tests/test_validation.py asks for one)
        return
    kind, allowed, what = RULES[name]
    bad_type = isinstance(value, bool) or not (isinstance(value, kind) or (kind is float and isinstance(value, int)))
    if bad_type:
        raise ConfigError(f"{option(name)} {value!r}: must be {what}, not a {type(value).__name__}")
    if kind is float and not math.isfinite(value):
        raise ConfigError(f"{option(name)} {value}: must be {what}, not {value}")
    if not allowed(value):
        raise ConfigError(f"{option(name)} {value}: must be {what}")


def _check_name(name: str, value: str, valid: Iterable[str]) -> None:
    valid = tuple(valid)
    if value not in valid:
        raise ConfigError(f"{option(name)} {value!r}: unknown {name}; valid: {', '.join(valid)}")


def check(
    run: RunConfig, train: TrainConfig, net: NetworkConfig, *, env_names: Iterable[str]
) -> None:
    """Raise `ConfigError` for the first value the run cannot use."""
    for config in (run, train, net):
        for f in dataclasses.fields(config):
            check_field(f.name, getattr(config, f.name))
    _check_name("env", run.env, env_names)
    _check_name("agent", run.agent, AGENTS)
    if train.buffer_episodes % train.num_envs:
        raise ConfigError(
            f"--buffer-episodes {train.buffer_episodes}: must be a multiple of --num-envs {train.num_envs} "
            "(whole rollouts are written at once)"
        )
    if train.obs_noise > 0 and not train.noise_segments.strip():
        raise ConfigError(f"--obs-noise {train.obs_noise}: needs --noise-segments (e.g. ee_pos,ee_rot,obj_pos)")


def check_env_support(train: TrainConfig, env: Any) -> None:
    """Raise `ConfigError` when `train` asks `env` for something it lacks (exploration starts,
    the proprio segments that get noise)."""
    unknown = [n for n in noise.parse_segments(train.noise_segments) if n not in env.observation_spec.segment_names]
    if unknown:
        raise ConfigError(
            f"{option('noise_segments')} {train.noise_segments}: env {env.name} has no segment {unknown[0]!r}; "
            f"its segments are {', '.join(env.observation_spec.segment_names)}"
        )
    if train.exploration_starts > 0 and not env.has_exploration_start:
        raise ConfigError(
            f"{option('exploration_starts')} {train.exploration_starts}: env {env.name} has no exploration start; "
            "must be 0"
        )
