"""DDPG + HER with UVFA, and with BidAL's forward and inverse models (paper Sec. III): one family.

Networks (`networks.make_networks`): an encoder φ for agents that see images, the actor, the critic and, with
the models, the forward model f and inverse model g. One update is two steps (`losses.make_losses`): the
representation loss (critic, Eq. 8, plus f and g, Eqs. 3 and 5) trains the encoder, critic, f and g at the
critic's learning rate, and passes its stopped φ(s) to the actor's step (Eq. 7), which trains the actor alone.
Acting reads the encoder and the actor; a transfer maps the rows of the encoder's proprio layer by segment name.
"""

from __future__ import annotations

import dataclasses
import functools

import jax

from bidal_jax.agents.family import Agent, Family, Loss, Step
from bidal_jax.losses import make_losses
from bidal_jax.networks import ACTION_LAYER, PROPRIO_LAYER, Networks, make_networks

UPDATE_ORDER = (
    Step("representation", ("encoder", "critic", "forward", "inverse"), lambda train: train.critic_lr,
         passes=("phi",)),
    Step("actor", ("actor",), lambda train: train.actor_lr),
)


def _networks(agent: Agent, config, proprio_size: int, goal_size: int, action_size: int, image_shape,
              *, models: bool) -> Networks:
    return make_networks(config, proprio_size, goal_size, action_size, image_shape,
                         uses_image=agent.uses_image, uses_proprio=agent.uses_proprio, models=models)


def _losses(networks: Networks, train, *, models: bool, curiosity: bool) -> dict[str, Loss]:
    losses = make_losses(networks, train if curiosity else dataclasses.replace(train, intrinsic_lambda=0.0), models)
    return {"representation": losses.representation, "actor": losses.actor}


def act(networks: Networks, params: dict, image: jax.Array | None, proprio: jax.Array, goal: jax.Array) -> jax.Array:
    """μ(ψ(s), η(g)) (paper Eq. 7) of φ(s), on normalised proprio and goals."""
    return networks.actor(params["actor"], networks.encode(params.get("encoder"), image, proprio), goal)


def family(models: bool, curiosity: bool = True) -> Family:
    """DDPG + HER, with BidAL's forward and inverse models if `models`; their intrinsic reward (Eq. 4) too unless
    `curiosity` is False (λ = 0: the models' losses still shape φ, the reward is r_e alone), which tells a gain of
    the representation losses apart from one of the curiosity reward."""
    return Family(
        make_networks=functools.partial(_networks, models=models),
        make_losses=functools.partial(_losses, models=models, curiosity=curiosity),
        update_order=UPDATE_ORDER,
        act=act,
        acting_networks=("encoder", "actor"),
        action_leaf=("actor", "params", ACTION_LAYER, "bias"),
        proprio_kernel=f"encoder/params/{PROPRIO_LAYER}/kernel",
    )


DDPG = family(models=False)
BIDAL = family(models=True)
BIDAL_NO_REWARD = family(models=True, curiosity=False)
