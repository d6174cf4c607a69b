"""Losses of DDPG + HER with the BidAL forward and inverse models (paper Sec. III).

- Intrinsic reward (Eq. 4): r_i = -λ/2 ‖f(φ(s_t), a_t) - φ(s_{t+1})‖².
- Critic (Eq. 8): (Q(s_t, a_t, g) - y_t)², y_t = clip(r_e + r_i + γ Q'(s_{t+1}, μ'(s_{t+1}, g), g),
  r_min/(1-γ), 0), with target networks Q', μ' on φ(s_{t+1}) of the target encoder φ' or, with
  `target_encoder` "online", of the online encoder, stopped (`TrainConfig.target_encoder`). The clip is HER's
  (the paper has none). HER's floor -1/(1-γ) would erase r_i wherever success is out of
  reach; ours is the return of the most negative reward r_min = -1 - 2λL (`min_reward`;
  docs/deviations.md).
- Forward model (Eq. 3): e = ½‖f(φ(s_t), a_t) - sg[φ(s_{t+1})]‖²; inverse model (Eq. 5):
  ½‖g(φ(s_t), φ(s_{t+1})) - a_t‖².
- Actor (Eq. 7, DDPG): -Q(s, μ(s, g), g) + c‖μ(s, g)‖², on a stopped φ(s).

The encoder φ learns from the critic, forward and inverse losses together (the
"representation loss"); the actor never changes it.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import chex
import jax
import jax.numpy as jnp

from bidal_jax.networks import Networks

MIN_EXTRINSIC_REWARD = -1.0  # the sparse r_e ∈ {-1, 0} (Eq. 6)


def intrinsic_reward(predicted_next_phi: jax.Array, next_phi: jax.Array, lam: float) -> jax.Array:
    """Paper Eq. 4: -λ/2 ‖φ̂(s_{t+1}) - φ(s_{t+1})‖², per transition."""
    chex.assert_equal_shape([predicted_next_phi, next_phi])
    return -0.5 * lam * jnp.sum(jnp.square(predicted_next_phi - next_phi), axis=-1)


def min_reward(lam: float, latent_size: int) -> float:
    """r_min, the most negative reward r = r_e + r_i (Eq. 8) of a prediction within φ's range.

    r_e ≥ -1 (Eq. 6). The encoder ends in tanh (φ(s) = tanh(LayerNorm(·)) ∈ [-1, 1]^L,
    networks.Encoder; every BidAL agent has it), so a prediction φ̂ in that box misses φ(s')
    by at most 2 per entry: ‖φ̂ - φ(s')‖² ≤ 4L and r_i ≥ -2λL (Eq. 4). The forward model's
    last layer is linear, so a prediction outside the box can give a reward below r_min,
    whose target may then be floored, as HER's clip floors any reward below its range.
    A fixed bound, not the batch's smallest reward: the floor of a return must not depend
    on which other transitions were sampled with it. λ = 0 (no forward model) gives HER's
    r_min = -1.
    """
    return MIN_EXTRINSIC_REWARD - 2.0 * lam * latent_size


def critic_target(reward: jax.Array, next_q: jax.Array, gamma: float, r_min: float) -> jax.Array:
    """Eq. 8's target y = r + γQ', clipped to [r_min/(1-γ), 0]: the range of the returns of
    rewards in [r_min, 0] (r_min from `min_reward`)."""
    chex.assert_equal_shape([reward, next_q])
    return jnp.clip(reward + gamma * next_q, r_min / (1.0 - gamma), 0.0)


def half_squared_error(pred: jax.Array, target: jax.Array) -> jax.Array:
    """½‖pred - target‖² per row (Eqs. 3 and 5)."""
    chex.assert_equal_shape([pred, target])
    return 0.5 * jnp.sum(jnp.square(pred - target), axis=-1)


@dataclasses.dataclass(frozen=True)
class Losses:
    """The losses of one update's two steps (`bidal_jax.agents.ddpg`), each `loss(trained, params, target_params,
    batch) -> (loss, aux)` (`agents.family.Loss`): `representation` trains the encoder, critic, forward and
    inverse models (`trained`, a dict of their subtrees) and returns the stopped φ(s) as aux "phi"; `actor` trains
    the actor (`trained`, its subtree) on `batch["phi"]`, with the critic of `params`."""

    representation: Callable
    actor: Callable


def make_losses(networks: Networks, config, bidal: bool) -> Losses:
    """The losses of `networks` with the learner's `config` (a `TrainConfig`); `bidal`: with the forward and
    inverse models and the intrinsic reward."""
    r_min = min_reward(config.intrinsic_lambda if bidal else 0.0, networks.latent_size)

    def encode_runs(enc_params, batch, steps: slice) -> jax.Array:
        """φ of the frames `steps` of each sampled run (`replay.sample`: a run's transitions share their frames)
        in one encoder pass: [runs, frames, latent]; slice(None) is every frame s_t ... s_{t+run}."""
        frames = batch.get("frames")  # without images each transition is a run of its own: proprio is cheap
        runs = batch["proprio"].shape[0] if frames is None else frames.shape[0]
        proprio, next_proprio = (batch[k].reshape(runs, -1, batch[k].shape[-1]) for k in ("proprio", "next_proprio"))
        proprio = jnp.concatenate([proprio, next_proprio[:, -1:]], axis=1)[:, steps]
        images = None if frames is None else frames[:, steps].reshape(-1, *frames.shape[2:])
        phis = networks.encode(enc_params, images, proprio.reshape(-1, proprio.shape[-1]))
        return phis.reshape(*proprio.shape[:2], -1)

    def per_transition(phis: jax.Array) -> jax.Array:
        return phis.reshape(-1, phis.shape[-1])

    def representation(params, _, target_params, batch):
        chex.assert_rank([batch["proprio"], batch["goal"], batch["action"]], 2)
        chex.assert_rank(batch["reward"], 1)
        # f and g (Eqs. 3 and 5) read the online φ(s_{t+1}), and so does the critic's target with the online
        # encoder: one pass over each run's frames; otherwise the critic alone reads online φ, of s_t
        if bidal or config.target_encoder == "online":
            phis = encode_runs(params.get("encoder"), batch, slice(None))
            phi, next_phi = per_transition(phis[:, :-1]), per_transition(phis[:, 1:])
        else:
            phi = per_transition(encode_runs(params.get("encoder"), batch, slice(None, -1)))
        if config.target_encoder == "online":
            target_next_phi = jax.lax.stop_gradient(next_phi)
        else:
            target_next_phi = per_transition(encode_runs(target_params.get("encoder"), batch, slice(1, None)))
        next_action = networks.actor(target_params["actor"], target_next_phi, batch["goal"])
        next_q = networks.critic(target_params["critic"], target_next_phi, next_action, batch["goal"])
        reward = batch["reward"]
        aux = {}
        loss = 0.0
        if bidal:
            predicted = networks.forward(params["forward"], phi, batch["action"])
            r_i = jax.lax.stop_gradient(intrinsic_reward(predicted, next_phi, config.intrinsic_lambda))
            forward_loss = half_squared_error(predicted, jax.lax.stop_gradient(next_phi)).mean()
            inverse_loss = half_squared_error(
                networks.inverse(params["inverse"], phi, next_phi), batch["action"]
            ).mean()
            loss = config.forward_weight * forward_loss + config.inverse_weight * inverse_loss
            reward = reward + r_i
            aux.update(forward_loss=forward_loss, inverse_loss=inverse_loss, intrinsic_reward=r_i.mean())
        y = jax.lax.stop_gradient(critic_target(reward, next_q, config.gamma, r_min))
        q = networks.critic(params["critic"], phi, batch["action"], batch["goal"])
        critic_loss = jnp.mean(jnp.square(q - y))
        # the batch's (relabelled) sparse r_e, beside r_i: their ratio is how much the intrinsic reward counts
        aux.update(critic_loss=critic_loss, q=q.mean(), extrinsic_reward=batch["reward"].mean(),
                   phi=jax.lax.stop_gradient(phi))
        return loss + critic_loss, aux

    def actor(actor_params, params, _, batch):
        phi, goal = batch["phi"], batch["goal"]
        chex.assert_rank([phi, goal], 2)
        action = networks.actor(actor_params, phi, goal)
        q = networks.critic(params["critic"], phi, action, goal)
        loss = -q.mean() + config.action_l2 * jnp.mean(jnp.square(action))
        return loss, {"actor_loss": loss}

    return Losses(representation=representation, actor=actor)
