"""The schedule of an epoch's phases (`train.make_train`): its cycles, then its evaluation, in one program.

An epoch is `cycles_per_epoch` cycles, each an exploring rollout of n_envs episodes that the learner then
learns from, and a deterministic evaluation of n_eval episodes. Where n_eval is a multiple of n_envs the
evaluation is the cycles' scan's last `chunks` phases, each a greedy rollout of the cycles' width through the
same traced env step, so that XLA compiles the physics once: a phase then explores and learns, or evaluates,
by a traced flag (`branch`), and the buffer is written in every phase (`Schedule.insert`). Otherwise (e.g. 128
of 2,048 envs) the evaluation is a rollout of its own after the scan, since padding it to the cycles' width
would cost physics every epoch; the flag is then a Python bool and only the branch it picks is traced. Either
way an evaluation draws its keys, starts and observation noise as one rollout of all n_eval episodes
(`acting.evaluate`) draws them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from bidal_jax import acting, noise, replay

Flag = bool | jax.Array  # a phase's `evaluating`: a Python bool (one branch traced) or a traced bool


def branch(pred: Flag, on_true: Callable, on_false: Callable, *operands) -> Any:
    """`lax.cond` on a traced `pred`; on a Python bool, the one branch it picks (the other is not traced)."""
    if isinstance(pred, bool):
        return (on_true if pred else on_false)(*operands)
    return jax.lax.cond(pred, on_true, on_false, *operands)


class Draws(NamedTuple):
    """The parts of a `TrainState` that a phase's start draws anew: its key, its evaluation key and the
    observation noise's state."""

    key: jax.Array
    eval_key: jax.Array
    noise: noise.NoiseState | None


class Phase(NamedTuple):
    """What a phase of an epoch (a cycle, or a chunk of the evaluation) rolls out, and with which keys: its
    episodes' starts, the rollout's key, and a cycle's keys of its updates and HER goals."""

    starts: acting.Starts
    key: jax.Array
    key_updates: jax.Array
    key_goals: jax.Array


@dataclasses.dataclass(frozen=True)
class Schedule:
    """One env shard's epoch: `cycles` cycles of `n_envs` episodes, then the evaluation of `n_eval` episodes (from
    `env.reset`), in `chunks` phases of the cycles' width at the end of their scan or (0 chunks) after it."""

    cycles: int
    n_envs: int
    n_eval: int
    exploration_starts: float = 0.0  # the fraction of a cycle's episodes begun by `env.exploration_reset`

    @property
    def chunks(self) -> int:
        """The evaluation's phases in the cycles' scan: n_eval / n_envs where n_envs divides n_eval, else 0."""
        return self.n_eval // self.n_envs if self.n_eval % self.n_envs == 0 else 0

    @property
    def width(self) -> int:
        """The episodes of an evaluation phase: the cycles' n_envs in the scan, all n_eval after it."""
        return self.n_envs if self.chunks else self.n_eval

    def evaluating(self, index: jax.Array) -> Flag:
        """Whether the scan's phase `index` is evaluation chunk index - cycles rather than cycle `index`."""
        return index >= self.cycles if self.chunks else False

    def rows(self, chunk: jax.Array | int) -> jax.Array:
        """The evaluation episodes of chunk `chunk` [width]: chunk·width onwards."""
        return chunk * self.width + jnp.arange(self.width)

    def per_episode(self, evaluating: Flag, chunk: jax.Array | int, draw: Callable[[int], jax.Array]) -> jax.Array:
        """A phase's share of `draw(n)` (something drawn for n episodes): a cycle's draw for its n_envs, or an
        evaluation chunk's rows of the draw for all n_eval, as one rollout of them draws it."""
        return branch(evaluating, lambda: draw(self.n_eval)[self.rows(chunk)], lambda: draw(self.n_envs))

    def evaluation_start(self, draws: Draws, chunk: jax.Array | int, own_key: Callable) -> tuple[Draws, Phase]:
        """The epoch's evaluation key (drawn by chunk 0, after the last cycle; `own_key` makes it an env shard's)
        and the starts of chunk `chunk`'s episodes, from `env.reset`; in the cycles' scan, with exploration starts,
        shaped as a cycle's with none picked."""
        key, key_eval = jax.random.split(draws.key)
        first = chunk == 0
        draws = draws._replace(key=jnp.where(first, key, draws.key),
                               eval_key=jnp.where(first, key_eval, draws.eval_key))
        key_eval = own_key(draws.eval_key)
        starts = acting.Starts(jax.random.split(jax.random.split(key_eval)[0], self.n_eval)[self.rows(chunk)])
        if self.exploration_starts > 0 and self.chunks:
            starts = starts._replace(eased=starts.reset, pick=jnp.zeros((self.n_envs,), bool))
        return draws, Phase(starts, key_eval, key_eval, key_eval)

    def insert(self, buffer: replay.ReplayState, episodes: dict, evaluating: Flag) -> replay.ReplayState:
        """`replay.insert` of a cycle's episodes. An evaluation chunk writes back what the slots hold and does
        not advance, so that the buffer is updated in place in every phase, outside `lax.cond` (whose outputs
        XLA would copy: hundreds of MB of images)."""
        if isinstance(evaluating, bool):
            return buffer if evaluating else replay.insert(buffer, episodes)
        held = jax.tree.map(lambda b: jax.lax.dynamic_slice_in_dim(b, buffer.position, self.n_envs),
                            buffer.episodes)
        kept = jax.tree.map(lambda e, h: jnp.where(evaluating, h, e.astype(h.dtype)), episodes, held)
        written = replay.insert(buffer, kept)
        return written.replace(position=jnp.where(evaluating, buffer.position, written.position),
                               size=jnp.where(evaluating, buffer.size, written.size))

    def evaluated(self, success: jax.Array, goals: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The evaluation episodes' success [n_eval] and goals [n_eval, G] of the scan's per-phase outputs
        (success [phases, n_envs], goals [phases, n_envs, G]): the rows of its evaluation chunks."""
        return success[self.cycles:].reshape(-1), goals[self.cycles:].reshape(-1, goals.shape[-1])


def learn_or_skip(learn: Callable) -> tuple[Callable, Callable]:
    """`learn(ts, *rollout) -> (ts without its buffer, metrics)` jitted (one trace serves the program and the
    shapes of its metrics), and an evaluation chunk's stand-in for it: nothing learned, zero metrics."""
    learned = jax.jit(learn)

    def skip(ts: Any, *rollout) -> tuple[Any, dict]:
        shapes = jax.eval_shape(learned, ts, *rollout)[1]
        return ts.replace(buffer=None), jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)

    return learned, skip
