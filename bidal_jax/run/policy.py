"""A trained policy, loaded from a run's checkpoint: `load_policy(run_dir, checkpoint=None)`.

Only what acting needs is read, with Orbax partial restore: the parameters of the networks the
agent's family acts with (`Family.acting_networks`; DDPG: the encoder and the actor), the
normalisers and the evaluation key. The replay buffer, optimiser states and target networks are
not, so a checkpoint whose buffer files were deleted still loads (`python -m experiments.evaluate`
is its command line). `load_noise` restores, for a run trained
with observation noise, the κ and σ its checkpoint's evaluation saw (paper Eq. 9), and `evaluate_seeds`
runs every seed's deterministic policy, under that noise or another.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any

import chex
import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import noise, normalizer
from bidal_jax.acting import ActingParams, Policy, evaluate, make_policy
from bidal_jax.config import Config
from bidal_jax.run import checkpoint

# the part of a training state that acting needs (all that `load_policy` reads)
ACTING_FIELDS = ("params", "proprio_norm", "goal_norm", "eval_key")


@dataclasses.dataclass(frozen=True)
class TrainedPolicy:
    """A trained agent as `load_policy` restores it; array leaves carry a leading seed axis [S].

    `policy(seed)` is the deterministic policy of one seed; `eval_key[seed]` is the key of
    that seed's evaluation at this checkpoint, so that `evaluate(env, policy(seed),
    eval_key[seed], config.train.eval_envs)` reproduces the run's logged eval success.
    """

    config: Config
    networks: Any  # the agent's (`Agent.networks`)
    params: ActingParams
    eval_key: jax.Array
    step: int

    @property
    def seeds(self) -> int:
        return int(self.eval_key.shape[0])

    def seed_params(self, seed: int) -> ActingParams:
        return jax.tree.map(lambda x: x[seed], self.params)

    def policy(self, seed: int = 0, explore: bool = False) -> Policy:
        return make_policy(self.networks, self.config, self.seed_params(seed), explore)


def _sizes(state: dict, action_leaf: tuple[str, ...]) -> dict:
    """The env facts that applying the networks needs, from a checkpoint's array metadata (no
    array is read; the action size from the family's `action_leaf`); the image shape only matters
    to `init`, which acting never calls."""
    return {
        "proprio_size": int(state["proprio_norm"]["mean"].shape[-1]),
        "goal_size": int(state["goal_norm"]["mean"].shape[-1]),
        "action_size": int(functools.reduce(lambda tree, key: tree[key], action_leaf, state["params"]).shape[-1]),
        "image_shape": None,
    }


def load_policy(run_dir: str, checkpoint_step: int | str | None = None) -> TrainedPolicy:
    """The acting parameters of a run: latest checkpoint, step N, or "best" (by eval success).

    Raises `CheckpointError`.
    """
    directory = os.path.join(run_dir, "checkpoints")
    step = checkpoint.resolve_step(directory, checkpoint_step)
    config = Config.from_dict(checkpoint.read_config(directory, step), f"checkpoint {step} in {directory}")
    saved = checkpoint.read_metadata(directory, step, ("state",))["state"]
    family = config.agent.family
    networks = config.agent.networks(config.network, **_sizes(saved, family.action_leaf))
    wanted = {name: saved[name] for name in ACTING_FIELDS}
    wanted["params"] = {k: v for k, v in saved["params"].items() if k in family.acting_networks}
    restored = checkpoint.restore_partial(directory, step, wanted)
    params = ActingParams(
        params=restored["params"],
        proprio_norm=normalizer.from_saved(restored["proprio_norm"]),
        goal_norm=normalizer.from_saved(restored["goal_norm"]),
    )
    return TrainedPolicy(config, networks, params, jnp.asarray(restored["eval_key"]), step)


def load_noise(run_dir: str, trained: TrainedPolicy) -> noise.NoiseState | None:
    """κ [S] and σ [S, F] of the observation noise (paper Eq. 9) at `trained`'s checkpoint, or None
    for a run trained without noise (empty `noise_segments`). Training saves the noise state its
    evaluation of that epoch used, so evaluating with it and `eval_key` reproduces the logged
    success. Orbax partial restore of the `noise` leaves alone. Raises `CheckpointError`."""
    segments = trained.config.train.noise_segments
    if not noise.parse_segments(segments):
        return None
    directory = os.path.join(run_dir, "checkpoints")
    saved = checkpoint.read_metadata(directory, trained.step, ("state",))["state"]
    if "noise" not in saved:
        raise checkpoint.CheckpointError(f"checkpoint {trained.step} in {directory} has no noise state "
                                         f"although its config names noise segments {segments!r}")
    restored = checkpoint.restore_partial(directory, trained.step, {"noise": saved["noise"]})["noise"]
    state = noise.NoiseState(kappa=jnp.asarray(restored["kappa"]), sigma=jnp.asarray(restored["sigma"]))
    chex.assert_shape(state.kappa, (trained.seeds,))
    chex.assert_rank(state.sigma, 2)
    return state


def evaluate_seeds(env, trained: TrainedPolicy, keys: jax.Array, episodes: int,
                   noise_state: noise.NoiseState | None = None,
                   segments: tuple[str, ...] | None = None) -> np.ndarray:
    """Success [S, episodes] of every seed's deterministic policy, seeds vmapped as in training; with
    `noise_state` (κ [S], σ [S, F]) each seed sees its observation noise as training's evaluation does,
    on the run's noise segments or on `segments` (F features in their order)."""
    if segments is None:
        segments = noise.parse_segments(trained.config.train.noise_segments)
    noise_map = noise.noise_map(env.observation_spec, segments, trained.config.train.noise_variant)

    def one(params, key, seed_noise):
        policy = make_policy(trained.networks, trained.config, params)
        observe = None if seed_noise is None else functools.partial(noise.observe, seed_noise, noise_map)
        return evaluate(env, policy, key, episodes, observe=observe)

    return np.asarray(jax.jit(jax.vmap(one))(trained.params, keys, noise_state))
