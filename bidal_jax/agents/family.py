"""What an algorithm family declares, so that the learner's generic parts can train, act and transfer it.

A `Family` names its networks (a factory whose `init(key)` returns one parameter subtree per network), which
loss trains which networks and in which order (`Step`s of one update), how it acts, and what loading a policy
and a transfer read of its parameters. An `Agent` is a family with what it observes; the registry of agents by
name is `bidal_jax.agents.AGENTS`. `train.make_train`, `acting.make_policy`, `run.policy` and `run.transfer`
read these declarations and name no network themselves.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax

# loss(trained, params, target_params, batch) -> (loss, aux): `trained` is the step's parameters (`Step.trained`),
# `params` all online parameters as the earlier steps of the update left them, `target_params` the targets
Loss = Callable[[Any, dict, dict, dict], tuple[jax.Array, dict]]


@dataclasses.dataclass(frozen=True)
class Step:
    """One gradient step of an update: the loss `name` trains `networks` (those the agent has) with an Adam
    optimiser of its own, whose state is `TrainState.opt_state[name]`.

    A step of one network optimises that network's subtree itself, a step of several a dict of their subtrees
    (the layout of the optimiser states in checkpoints). `passes` names entries of the loss's aux that the later
    steps of the update read from their batch (e.g. the stopped φ(s)); they are not logged."""

    name: str
    networks: tuple[str, ...]
    learning_rate: Callable[[Any], float]  # of the run's `TrainConfig`
    passes: tuple[str, ...] = ()

    def trained(self, params: dict) -> Any:
        """The parameters this step trains, out of all of them."""
        if len(self.networks) == 1:
            return params[self.networks[0]]
        return {k: v for k, v in params.items() if k in self.networks}

    def merged(self, params: dict, trained: Any) -> dict:
        """`params` with this step's parameters replaced by `trained` (pure)."""
        if len(self.networks) == 1:
            return {**params, self.networks[0]: trained}
        return {**params, **trained}


@dataclasses.dataclass(frozen=True)
class Family:
    """An algorithm family, declared in one module (`bidal_jax.agents.ddpg`).

    - `make_networks(agent, network_config, proprio_size, goal_size, action_size, image_shape)`: the networks,
      an object whose `init(key)` returns {network name: parameter subtree}; the other callables get it back.
    - `make_losses(networks, train_config) -> {step name: Loss}`: a loss for each step of `update_order`.
    - `update_order`: the steps of one gradient update, in order; then every target network moves (Polyak).
    - `act(networks, params, image, proprio, goal) -> actions [N, A] in [-1, 1]`: the deterministic policy on
      normalised proprio and goals (`image` None for an agent without images).
    - `acting_networks`: the networks `act` reads (all that loading a trained policy restores).
    - `action_leaf`: the path in the parameters of a leaf whose last axis is the action size.
    - `proprio_kernel`: the path in the parameters ("network/.../kernel", as `checkpoint.leaf_name` writes it) of
      the leaf whose rows are the proprio features, which a transfer maps by segment name; an agent whose
      networks never read proprio has no such leaf.
    """

    make_networks: Callable[..., Any]
    make_losses: Callable[[Any, Any], dict[str, Loss]]
    update_order: tuple[Step, ...]
    act: Callable[..., jax.Array]
    acting_networks: tuple[str, ...]
    action_leaf: tuple[str, ...]
    proprio_kernel: str


@dataclasses.dataclass(frozen=True)
class Agent:
    """An algorithm family and what it observes: images (the env renders them), proprio."""

    family: Family
    uses_image: bool
    uses_proprio: bool

    def networks(self, config: Any, proprio_size: int, goal_size: int, action_size: int, image_shape: Any) -> Any:
        """This agent's networks for the sizes of an env (`Family.make_networks`)."""
        return self.family.make_networks(self, config, proprio_size, goal_size, action_size, image_shape)
