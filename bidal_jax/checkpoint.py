"""Orbax checkpoints of the whole `TrainState` plus the run's config (DESIGN.md).

A checkpoint directory `<run>/checkpoints/<epoch>/` holds the state pytree (all
parameters, optimiser states, targets, normalisers, replay buffer, rng, counters) and
the config as JSON. Orbax writes each step to a temporary directory and renames it when
complete, so a process killed mid-save leaves the previous checkpoint intact.
`restore_subtrees` lifts named parameter subtrees (encoder, forward, inverse, ...) out
of a checkpoint for transfer.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import orbax.checkpoint as ocp


class CheckpointError(Exception):
    """A checkpoint that cannot be used: missing, damaged, or written for another run."""


def manager(directory: str, max_to_keep: int = 2) -> ocp.CheckpointManager:
    return ocp.CheckpointManager(
        os.path.abspath(directory),
        options=ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True),
        item_names=("state", "config"),
    )


def save(mngr: ocp.CheckpointManager, step: int, state: Any, config: dict) -> None:
    """Save `state` and `config` as `step` and wait until it is on disk."""
    mngr.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(config)))
    mngr.wait_until_finished()


def latest_step(directory: str) -> int | None:
    if not os.path.isdir(directory):
        return None
    return manager(directory).latest_step()


def read_config(directory: str, step: int | None = None) -> dict:
    """The config stored with a checkpoint (the latest one by default)."""
    mngr = manager(directory)
    step = mngr.latest_step() if step is None else step
    if step is None:
        raise CheckpointError(f"no checkpoint in {directory}")
    try:
        return mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
    except Exception as err:  # orbax raises many types for damaged files
        raise CheckpointError(f"checkpoint {step} in {directory} has no readable config: {err}") from err


def restore(directory: str, abstract_state: Any, step: int | None = None) -> tuple[Any, dict, int]:
    """Restore (state, config, step) shaped like `abstract_state` (latest step by default)."""
    mngr = manager(directory)
    step = mngr.latest_step() if step is None else step
    if step is None:
        raise CheckpointError(f"no checkpoint in {directory}")
    target = jax.tree.map(ocp.utils.to_shape_dtype_struct, abstract_state)
    try:
        restored = mngr.restore(
            step, args=ocp.args.Composite(state=ocp.args.StandardRestore(target), config=ocp.args.JsonRestore())
        )
    except Exception as err:
        raise CheckpointError(f"checkpoint {step} in {directory} cannot be restored: {err}") from err
    return restored["state"], restored["config"], step


def restore_subtrees(directory: str, abstract_state: Any, names: tuple[str, ...], step: int | None = None) -> dict:
    """The parameter subtrees `names` of a checkpoint, e.g. ("encoder", "forward", "inverse")."""
    state, _, _ = restore(directory, abstract_state, step)
    missing = [n for n in names if n not in state.params]
    if missing:
        raise CheckpointError(f"checkpoint has no parameter subtrees {missing}; it has {sorted(state.params)}")
    return {n: state.params[n] for n in names}
