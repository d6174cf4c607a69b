"""Losses and intrinsic reward against hand-computed values (bidal_jax/losses.py)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bidal_jax import losses
from bidal_jax.agents import ddpg
from bidal_jax.config import AGENTS, NetworkConfig, TrainConfig


def test_intrinsic_reward_by_hand():
    pred = jnp.array([[1.0, 2.0], [0.0, 0.0]])
    nxt = jnp.array([[0.0, 0.0], [3.0, 4.0]])
    # -λ/2 ||·||²: λ = 0.5 → -0.25 * 5 and -0.25 * 25
    np.testing.assert_allclose(losses.intrinsic_reward(pred, nxt, 0.5), [-1.25, -6.25])


def test_min_reward_by_hand():
    # r_e ≥ -1; a prediction within [-1, 1]^L misses by ≤ 2 per entry: r_i ≥ -λ/2 · 4L = -2λL
    assert losses.min_reward(0.1, 50) == pytest.approx(-11.0)
    assert losses.min_reward(0.3, 8) == pytest.approx(-5.8)
    assert losses.min_reward(0.0, 50) == -1.0  # no intrinsic reward: HER's floor


def test_min_reward_holds_for_every_bidal_agent():
    """`min_reward` assumes φ(s) ∈ [-1, 1]^L, i.e. every BidAL agent has the tanh encoder."""
    assert all(agent.uses_image for agent in AGENTS.values() if agent.family is ddpg.BIDAL)
    nets = AGENTS["visual_bidal"].networks(NetworkConfig(conv_channels=4, latent_size=8), 4, 2, 2, (42, 42, 1))
    params = nets.init(jax.random.PRNGKey(0))
    image = jnp.full((2, 42, 42, 1), 255, jnp.uint8)  # with weights scaled up until tanh saturates
    phi = nets.encode(jax.tree.map(lambda x: 1e3 * x, params["encoder"]), image, jnp.zeros((2, 4)))
    assert float(jnp.abs(phi).max()) <= 1.0


def test_critic_target_without_intrinsic_reward_is_hers():
    """r_min = -1 (r_i = 0): the old clip to [-1/(1-γ), 0]."""
    r = jnp.array([-1.0, 0.0, -1.0])
    q = jnp.array([-10.0, 5.0, -100.0])
    # γ = 0.9 → y = r + 0.9 q, clipped to [-10, 0]
    np.testing.assert_allclose(losses.critic_target(r, q, 0.9, -1.0), [-10.0, 0.0, -10.0])
    np.testing.assert_allclose(losses.critic_target(jnp.array([-1.0]), jnp.array([-2.0]), 0.9, -1.0), [-2.8])


def test_critic_target_keeps_the_intrinsic_reward_where_success_is_out_of_reach():
    """r_e = -1 and Q' at HER's floor -1/(1-γ): y still differs by r_i; the ceiling 0 holds."""
    gamma, r_min = 0.9, losses.min_reward(0.1, 50)  # r_min = -11: floor -110
    r_i = jnp.array([0.0, -0.5, -2.0])
    q_floor = jnp.full(3, -10.0)
    # -1 + r_i + 0.9 · (-10) = -10 + r_i; the old clip [-10, 0] made all three -10
    np.testing.assert_allclose(losses.critic_target(-1.0 + r_i, q_floor, gamma, r_min), [-10.0, -10.5, -12.0])
    np.testing.assert_allclose(losses.critic_target(-1.0 + r_i, q_floor, gamma, -1.0), [-10.0, -10.0, -10.0])
    # the new floor r_min/(1-γ) = -110 and the ceiling 0
    y = losses.critic_target(jnp.array([-11.0, -0.1]), jnp.array([-500.0, 3.0]), gamma, r_min)
    np.testing.assert_allclose(y, [-110.0, 0.0])


def test_half_squared_error_by_hand():
    np.testing.assert_allclose(losses.half_squared_error(jnp.array([[1.0, -1.0]]), jnp.array([[0.0, 1.0]])), [2.5])


def _tiny_batch(b=3, d=4, g=2, a=2, image=True):
    rng = np.random.default_rng(0)
    batch = {
        "proprio": jnp.asarray(rng.normal(size=(b, d)), jnp.float32),
        "next_proprio": jnp.asarray(rng.normal(size=(b, d)), jnp.float32),
        "goal": jnp.asarray(rng.normal(size=(b, g)), jnp.float32),
        "action": jnp.asarray(rng.uniform(-1, 1, size=(b, a)), jnp.float32),
        "reward": jnp.array([-1.0, 0.0, -1.0]),
    }
    if image:
        # each transition its own run: its s_t and s_{t+1} (replay.sample's "frames" with sample_run 1)
        batch["frames"] = jnp.asarray(rng.integers(0, 255, size=(b, 2, 42, 42, 1)), jnp.uint8)
    return batch


def _counting(nets):
    """`nets` whose `encode` records the frames of each call, and that record."""
    seen = []

    def encode(params, image, proprio):
        seen.append(image.shape[0])
        return nets.encode(params, image, proprio)

    return dataclasses.replace(nets, encode=encode), seen


def test_representation_loss_matches_a_hand_composition():
    """The loss equals critic MSE + forward + inverse losses computed here from the networks."""
    cfg = TrainConfig(gamma=0.9, intrinsic_lambda=0.3, forward_weight=0.7, inverse_weight=0.2,
                      target_encoder="target")
    nets = AGENTS["multimodal_bidal"].networks(NetworkConfig(conv_channels=4, latent_size=8), 4, 2, 2, (42, 42, 1)
    )
    params = nets.init(jax.random.PRNGKey(0))
    target = jax.tree.map(lambda x: x * 0.9, params)
    batch = _tiny_batch()
    loss, aux = losses.make_losses(nets, cfg, bidal=True).representation(params, params, target, batch)

    phi = nets.encode(params["encoder"], batch["frames"][:, 0], batch["proprio"])
    nphi = nets.encode(params["encoder"], batch["frames"][:, 1], batch["next_proprio"])
    tnphi = nets.encode(target["encoder"], batch["frames"][:, 1], batch["next_proprio"])
    pred = nets.forward(params["forward"], phi, batch["action"])
    r_i = -0.15 * np.sum((np.asarray(pred) - np.asarray(nphi)) ** 2, axis=-1)
    nq = nets.critic(target["critic"], tnphi, nets.actor(target["actor"], tnphi, batch["goal"]), batch["goal"])
    # r_min = -1 - 2 · 0.3 · 8 = -5.8 → floor -58
    y = np.clip(np.asarray(batch["reward"]) + r_i + 0.9 * np.asarray(nq), -58.0, 0.0)
    q = np.asarray(nets.critic(params["critic"], phi, batch["action"], batch["goal"]))
    fwd = np.mean(0.5 * np.sum((np.asarray(pred) - np.asarray(nphi)) ** 2, axis=-1))
    a_hat = np.asarray(nets.inverse(params["inverse"], phi, nphi))
    inv = np.mean(0.5 * np.sum((a_hat - np.asarray(batch["action"])) ** 2, axis=-1))
    expected = np.mean((q - y) ** 2) + 0.7 * fwd + 0.2 * inv
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    np.testing.assert_allclose(float(aux["intrinsic_reward"]), r_i.mean(), rtol=1e-5)
    np.testing.assert_allclose(float(aux["forward_loss"]), fwd, rtol=1e-5)
    np.testing.assert_allclose(float(aux["inverse_loss"]), inv, rtol=1e-5)


@pytest.mark.parametrize("agent, floor", [("multimodal_bidal", -58.0), ("multimodal_baseline", -10.0)])
def test_representation_loss_floors_the_target_at_the_agents_r_min(agent, floor):
    """Q' = -1000 everywhere: y is the floor r_min/(1-γ), -(1 + 2·0.3·8)/0.1 with BidAL, -1/0.1 without."""
    cfg = TrainConfig(gamma=0.9, intrinsic_lambda=0.3)
    nets = AGENTS[agent].networks(NetworkConfig(conv_channels=4, latent_size=8), 4, 2, 2, (42, 42, 1))
    params = nets.init(jax.random.PRNGKey(0))
    head = params["critic"]["params"]["Dense_2"]  # the critic's output layer (two hidden layers)
    constant_head = {"kernel": jnp.zeros_like(head["kernel"]), "bias": jnp.full_like(head["bias"], -1000.0)}
    target = {**params, "critic": {"params": {**params["critic"]["params"], "Dense_2": constant_head}}}
    batch = _tiny_batch()
    loss = losses.make_losses(nets, cfg, bidal=AGENTS[agent].family is ddpg.BIDAL).representation
    _, aux = loss(params, params, target, batch)
    phi = nets.encode(params["encoder"], batch["frames"][:, 0], batch["proprio"])
    q = np.asarray(nets.critic(params["critic"], phi, batch["action"], batch["goal"]))
    np.testing.assert_allclose(float(aux["critic_loss"]), np.mean((q - floor) ** 2), rtol=1e-5)


def test_actor_loss_has_the_action_penalty_and_leaves_the_encoder_alone():
    cfg = TrainConfig(action_l2=2.0)
    nets = AGENTS["proprio_baseline"].networks(NetworkConfig(), 4, 2, 2, (42, 42, 1))
    params = nets.init(jax.random.PRNGKey(1))
    batch = {**_tiny_batch(image=False), "phi": _tiny_batch(image=False)["proprio"]}
    loss, _ = losses.make_losses(nets, cfg, bidal=False).actor(params["actor"], params, params, batch)
    a = nets.actor(params["actor"], batch["phi"], batch["goal"])
    q = nets.critic(params["critic"], batch["phi"], a, batch["goal"])
    np.testing.assert_allclose(float(loss), float(-q.mean() + 2.0 * jnp.mean(a**2)), rtol=1e-6)
    assert "encoder" not in params


@pytest.mark.parametrize("agent, frames", [("multimodal_bidal", [6, 3]), ("multimodal_baseline", [3, 3])])
def test_the_online_encoder_reads_the_next_frame_only_for_bidals_models(agent, frames):
    """BidAL's f and g read the online φ(s_{t+1}), so its update encodes (s_t, s_{t+1}) online in one pass; a
    baseline's critic needs φ(s_t) alone online (φ(s_{t+1}) comes from the target encoder): 3 frames, not 6. The
    loss is the hand-composed one either way (`target_encoder` "target")."""
    cfg = TrainConfig(gamma=0.9, target_encoder="target")
    nets = AGENTS[agent].networks(NetworkConfig(conv_channels=4, latent_size=8), 4, 2, 2, (42, 42, 1))
    counting, seen = _counting(nets)
    params = nets.init(jax.random.PRNGKey(0))
    target = jax.tree.map(lambda x: x * 0.9, params)
    batch = _tiny_batch()
    bidal = AGENTS[agent].family is ddpg.BIDAL
    loss, _ = losses.make_losses(counting, cfg, bidal).representation(
        params, params, target, batch)
    assert seen == frames
    if not bidal:
        phi = nets.encode(params["encoder"], batch["frames"][:, 0], batch["proprio"])
        tnphi = nets.encode(target["encoder"], batch["frames"][:, 1], batch["next_proprio"])
        nq = nets.critic(target["critic"], tnphi, nets.actor(target["actor"], tnphi, batch["goal"]), batch["goal"])
        y = np.clip(np.asarray(batch["reward"]) + 0.9 * np.asarray(nq), -10.0, 0.0)
        q = np.asarray(nets.critic(params["critic"], phi, batch["action"], batch["goal"]))
        np.testing.assert_allclose(float(loss), np.mean((q - y) ** 2), rtol=1e-5)


@pytest.mark.parametrize("agent", ["multimodal_bidal", "multimodal_baseline"])
def test_the_online_target_encoder_reads_the_online_next_phi_and_no_target_encoder(agent):
    """`target_encoder` "online": the critic's target reads the online φ(s_{t+1}), stopped: each frame is encoded
    once, in one pass (BidAL's f and g read that φ(s_{t+1}) too); the target encoder's parameters change
    nothing."""
    cfg = TrainConfig(gamma=0.9, intrinsic_lambda=0.3, target_encoder="online")
    nets = AGENTS[agent].networks(NetworkConfig(conv_channels=4, latent_size=8), 4, 2, 2, (42, 42, 1))
    counting, seen = _counting(nets)
    params = nets.init(jax.random.PRNGKey(0))
    target = jax.tree.map(lambda x: x * 0.9, params)
    other = {**target, "encoder": jax.tree.map(lambda x: x * -3.0, params["encoder"])}
    batch, bidal = _tiny_batch(), AGENTS[agent].family is ddpg.BIDAL
    loss = losses.make_losses(counting, cfg, bidal).representation
    value, _ = loss(params, params, target, batch)
    assert seen == [6]
    assert float(loss(params, params, other, batch)[0]) == pytest.approx(float(value), rel=1e-6)

    nphi = nets.encode(params["encoder"], batch["frames"][:, 1], batch["next_proprio"])
    nq = nets.critic(target["critic"], nphi, nets.actor(target["actor"], nphi, batch["goal"]), batch["goal"])
    phi = nets.encode(params["encoder"], batch["frames"][:, 0], batch["proprio"])
    reward = np.asarray(batch["reward"])
    if bidal:
        pred = nets.forward(params["forward"], phi, batch["action"])
        reward = reward - 0.15 * np.sum((np.asarray(pred) - np.asarray(nphi)) ** 2, axis=-1)
    floor = losses.min_reward(0.3 if bidal else 0.0, 8) / 0.1
    y = np.clip(reward + 0.9 * np.asarray(nq), floor, 0.0)
    q = np.asarray(nets.critic(params["critic"], phi, batch["action"], batch["goal"]))
    critic = float(loss(params, params, target, batch)[1]["critic_loss"])
    np.testing.assert_allclose(critic, np.mean((q - y) ** 2), rtol=1e-5)


@pytest.mark.parametrize("agent, encoder, frames", [("multimodal_bidal", "online", [8]),
                                                     ("multimodal_bidal", "target", [8, 6]),
                                                     ("multimodal_baseline", "target", [6, 6])])
def test_runs_that_share_frames_give_the_loss_and_gradients_of_their_transitions(agent, encoder, frames):
    """Two runs of 3 consecutive transitions (`TrainConfig.sample_run` 3) encode their 8 frames once (the target
    encoder their 6 next frames), and give the loss and gradients of the same 6 transitions with their own frames."""
    rng = np.random.default_rng(3)
    images = jnp.asarray(rng.integers(0, 255, size=(2, 4, 42, 42, 1)), jnp.uint8)
    proprio = jnp.asarray(rng.normal(size=(2, 4, 4)), jnp.float32)
    single = {**_tiny_batch(b=6), "reward": jnp.array([-1.0, 0.0, -1.0, -1.0, 0.0, 0.0])}
    runs = {**single, "frames": images, "proprio": proprio[:, :3].reshape(6, 4),
            "next_proprio": proprio[:, 1:].reshape(6, 4)}
    single.update(frames=jnp.stack([images[:, :3], images[:, 1:]], axis=2).reshape(6, 2, 42, 42, 1),
                  proprio=runs["proprio"], next_proprio=runs["next_proprio"])
    cfg = TrainConfig(gamma=0.9, intrinsic_lambda=0.3, target_encoder=encoder)
    nets = AGENTS[agent].networks(NetworkConfig(conv_channels=4, latent_size=8), 4, 2, 2, (42, 42, 1))
    counting, seen = _counting(nets)
    params = nets.init(jax.random.PRNGKey(0))
    target = jax.tree.map(lambda x: x * 0.9, params)
    loss = losses.make_losses(counting, cfg, AGENTS[agent].family is ddpg.BIDAL).representation
    (value, aux), grads = jax.value_and_grad(loss, has_aux=True)(params, params, target, runs)
    assert seen == frames
    (expected, expected_aux), expected_grads = jax.value_and_grad(loss, has_aux=True)(params, params, target, single)
    np.testing.assert_allclose(float(value), float(expected), rtol=1e-5)
    np.testing.assert_allclose(aux["phi"], expected_aux["phi"], rtol=1e-5, atol=1e-6)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6), grads, expected_grads)
