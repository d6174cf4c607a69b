"""A new algorithm is one module's `Family` and a registry entry (bidal_jax/agents): a toy agent registered
that way trains through the whole command line for one epoch, and its trained policy loads."""

import csv
import dataclasses
import os

import flax.linen as nn
import jax
import jax.numpy as jnp
import pytest

from bidal_jax import agents
from bidal_jax.agents import Agent, Family, Step
from bidal_jax.run.policy import load_policy
from experiments import run
from tests.helpers import TINY


@dataclasses.dataclass(frozen=True)
class ToyNetworks:
    """A linear policy of (proprio, goal) and a linear Q of (proprio, action, goal)."""

    init: object
    policy: object
    value: object


def toy_networks(agent, config, proprio_size, goal_size, action_size, image_shape):
    policy, value = nn.Dense(action_size), nn.Dense(1)

    def init(key):
        key_policy, key_value = jax.random.split(key)
        return {"policy": policy.init(key_policy, jnp.zeros((1, proprio_size + goal_size))),
                "value": value.init(key_value, jnp.zeros((1, proprio_size + action_size + goal_size)))}

    return ToyNetworks(
        init=init,
        policy=lambda params, proprio, goal: jnp.tanh(policy.apply(params, jnp.concatenate([proprio, goal], -1))),
        value=lambda params, proprio, action, goal: value.apply(params, jnp.concatenate([proprio, action, goal], -1)),
    )


def toy_losses(networks, train):
    def value_loss(value, params, target_params, batch):
        next_action = networks.policy(target_params["policy"], batch["next_proprio"], batch["goal"])
        next_q = networks.value(target_params["value"], batch["next_proprio"], next_action, batch["goal"])[:, 0]
        y = jax.lax.stop_gradient(batch["reward"] + train.gamma * next_q)
        loss = jnp.mean(jnp.square(networks.value(value, batch["proprio"], batch["action"], batch["goal"])[:, 0] - y))
        return loss, {"value_loss": loss}

    def policy_loss(policy, params, target_params, batch):
        action = networks.policy(policy, batch["proprio"], batch["goal"])
        loss = -jnp.mean(networks.value(params["value"], batch["proprio"], action, batch["goal"]))
        return loss, {"policy_loss": loss}

    return {"value": value_loss, "policy": policy_loss}


TOY = Family(
    make_networks=toy_networks,
    make_losses=toy_losses,
    update_order=(Step("value", ("value",), lambda train: train.critic_lr),
                  Step("policy", ("policy",), lambda train: train.actor_lr)),
    act=lambda networks, params, image, proprio, goal: networks.policy(params["policy"], proprio, goal),
    acting_networks=("policy",),
    action_leaf=("policy", "params", "bias"),
    proprio_kernel="policy/params/kernel",
)


@pytest.fixture
def toy_agent(monkeypatch):
    monkeypatch.setitem(agents.AGENTS, "toy", Agent(TOY, uses_image=False, uses_proprio=True))


def test_a_registered_toy_agent_trains_one_epoch_and_its_policy_loads(toy_agent, tmp_path):
    run_dir = str(tmp_path / "toy")
    assert run.main([*TINY, "--agent", "toy", "--epochs", "1", "--run-dir", run_dir]) == 0  # the last --agent
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        row = next(csv.DictReader(f))
    assert {"value_loss", "policy_loss"} <= set(row) and "critic_loss" not in row
    trained = load_policy(run_dir)
    assert set(trained.params.params) == {"policy"}  # its acting networks, nothing else
    assert trained.networks.policy is not None and trained.params.params["policy"]["params"]["kernel"].shape[-1] == 2
