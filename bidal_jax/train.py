"""The training program as pure functions: `make_train(env, config) -> (init, epoch)`.

`epoch` is ONE jit-able function: a `lax.scan` over cycles of (vectorised rollout of all
parallel envs with exploration, buffer insert, normaliser update, n gradient updates,
target update after every gradient step), then deterministic evaluation rollouts. Where
`eval_envs` is a multiple of `num_envs` the evaluation is the scan's last phases, chunks of the
cycles' width, and every phase is one `acting.rollout` with `acting.make_policy` (exploring
switched off by a traced flag): the program steps the env in one place and XLA compiles the
physics once. Otherwise it is a rollout of its own after the scan. The agent's family (`bidal_jax.agents`)
declares the networks, the losses and the order of an update's steps; DDPG + BidAL's are
`losses.py`'s (paper Eqs. 3-5, 7, 8). HER relabels with the `future` strategy inside `replay.sample`.

Seeds are a `vmap` over `init`/`epoch`, and env shards a `shard_map` over the mesh axis
`ENV_AXIS`; both are laid out on devices by the run machinery (`bidal_jax.run.devices`).
With k env shards each shard steps its share of the envs, keeps its share of the replay
buffer, draws its share of each batch and averages its gradients with the other shards'
(`Shards`), so the shards hold identical parameters, as data-parallel training does.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from bidal_jax import acting, noise, normalizer, replay
from bidal_jax.config import Config, ConfigError

SEED_AXIS, ENV_AXIS = "seeds", "envs"  # the device mesh's axes (`bidal_jax.run.devices`)


@struct.dataclass
class TrainState:
    """Everything a run needs to continue: parameters, optimisers, targets, data, rng."""

    params: dict
    target_params: dict
    opt_state: dict
    proprio_norm: normalizer.NormalizerState
    goal_norm: normalizer.NormalizerState
    buffer: replay.ReplayState
    key: jax.Array
    eval_key: jax.Array  # the key of the latest evaluation (acting.evaluate reproduces it)
    noise: noise.NoiseState | None  # κ and σ of the observation noise (paper Eq. 9); None without noise
    env_steps: jax.Array
    updates: jax.Array
    epoch: jax.Array


@dataclasses.dataclass(frozen=True)
class Shards:
    """How one of `count` env shards agrees with the others, through collectives over `ENV_AXIS`
    (inside a `shard_map`); with one shard each is the identity and no collective is traced."""

    count: int

    def own_key(self, key: jax.Array) -> jax.Array:
        """This shard's key: `key` itself when unsharded."""
        return key if self.count == 1 else jax.random.fold_in(key, jax.lax.axis_index(ENV_AXIS))

    def everyone(self, x: jax.Array) -> jax.Array:
        """x [n, ...] of every shard, concatenated: [k·n, ...]."""
        return x if self.count == 1 else jax.lax.all_gather(x, ENV_AXIS, tiled=True)

    def average(self, tree: Any) -> Any:
        """The mean over shards of a pytree (gradients, metrics)."""
        return tree if self.count == 1 else jax.lax.pmean(tree, ENV_AXIS)


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


HITS, COUNT = "_hits", "_count"  # a cycle's successes and episodes of a start kind, summed into its rate by `epoch`


def start_kinds(pick: jax.Array) -> dict[str, jax.Array]:
    """The training episodes of each start kind, as masks [n] of `acting.Starts.pick`: "train_success_held" begun by
    `env.exploration_reset` (nicol_lift: the cube in the hand, HER's pick-and-place protocol) and
    "train_success_table" by `env.reset`, so that a run shows how far the held starts alone carry its success."""
    return {"train_success_held": pick, "train_success_table": jnp.logical_not(pick)}


def branch(pred: bool | jax.Array, on_true: Callable, on_false: Callable, *operands) -> Any:
    """`lax.cond` on a traced `pred`; on a Python bool, the one branch it picks (the other is not traced)."""
    if isinstance(pred, bool):
        return (on_true if pred else on_false)(*operands)
    return jax.lax.cond(pred, on_true, on_false, *operands)


# `jax.named_scope`s of an epoch's parts, by which profiles attribute its kernels (experiments/bench/tracing.py)
UPDATE_SCOPE, REPLAY_SCOPE, OPTIMISER_SCOPE, TARGET_SCOPE = "update", "replay", "optimiser", "target"
EVALUATION_SCOPE, NORMALISER_SCOPE = "evaluation", "normalisers"


def optimizer(lr: float, grad_clip: float) -> optax.GradientTransformation:
    """Adam at rate `lr` on gradients clipped to global norm `grad_clip`, over a network group's parameters
    raveled into one vector (`optax.flatten`): the same update (Adam is elementwise, the norm spans every
    element either way) as one set of operations instead of one per parameter array, a smaller program to
    compile. Checkpoints saved with one moment per parameter array restore raveled (`checkpoint.restore`)."""
    return optax.flatten(optax.chain(optax.clip_by_global_norm(grad_clip), optax.adam(lr)))


def polyak(target: Any, online: Any, tau: float) -> Any:
    """target ← (1 - τ) target + τ online."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def her_probability(her_k: int) -> float:
    """HER's `future` ratio k as the probability of relabelling a goal: 1 - 1/(1+k)."""
    return 1.0 - 1.0 / (1.0 + her_k)


@dataclasses.dataclass(frozen=True)
class Learner:
    """An agent's networks, its optimisers by update step name, and `update(ts, key) -> (ts, metrics)`: one
    gradient step of each of the family's `update_order` steps on a batch sampled from `ts.buffer`."""

    networks: Any
    optimizers: dict[str, optax.GradientTransformation]
    update: Callable


def make_learner(env, config: Config, shards: Shards) -> Learner:
    """The learner of `config`'s agent on `env`'s observations, one of `shards.count` env shards (it draws its
    share of each batch and averages its gradients with the others'): what `make_train` runs after each rollout,
    and what `experiments.bench.updates` times alone."""
    train, agent, spec = config.train, config.agent, env.observation_spec
    networks = agent.networks(config.network, spec.proprio_size, spec.goal_size, env.action_size, spec.image_shape)
    losses, steps = agent.family.make_losses(networks, train), agent.family.update_order
    optimizers = {step.name: optimizer(step.learning_rate(train), train.grad_clip) for step in steps}
    future_p, n_batch = her_probability(train.her_k), train.batch_size // shards.count

    @jax.named_scope(UPDATE_SCOPE)
    def update(ts: TrainState, key: jax.Array) -> tuple[TrainState, dict]:
        """One gradient step of each of the family's `update_order` steps (DDPG + BidAL: the representation
        group, encoder, critic, f and g, then the actor), each on the parameters the earlier ones left."""
        with jax.named_scope(REPLAY_SCOPE):
            batch = replay.sample(ts.buffer, shards.own_key(key), n_batch, future_p, env.compute_reward,
                                   train.sample_run)
            batch = normalizer.normalize_batch(batch, ts.proprio_norm, ts.goal_norm, train.clip_obs)
        params, opt_state, metrics = ts.params, {}, {}
        for step in steps:
            trained = step.trained(params)
            grads, aux = jax.grad(losses[step.name], has_aux=True)(trained, params, ts.target_params, batch)
            with jax.named_scope(OPTIMISER_SCOPE):
                updates, opt_state[step.name] = optimizers[step.name].update(
                    shards.average(grads), ts.opt_state[step.name], trained)
                params = step.merged(params, optax.apply_updates(trained, updates))
            batch = {**batch, **{name: aux.pop(name) for name in step.passes}}
            metrics.update(aux)
        with jax.named_scope(TARGET_SCOPE):
            target_params = polyak(ts.target_params, params, train.tau)
        ts = ts.replace(params=params, target_params=target_params, opt_state=opt_state, updates=ts.updates + 1)
        return ts, metrics

    return Learner(networks, optimizers, update)


def make_train(env, config: Config, env_shards: int = 1):
    """Build `init(key) -> TrainState` and `epoch(TrainState) -> (TrainState, metrics)`.

    With `env_shards` k > 1 the functions are one shard's part of a `shard_map` over the mesh
    axis `ENV_AXIS` (`bidal_jax.run.devices.make_seeded`): k divides the envs, evaluation envs,
    batch and buffer (`devices.device_layout` picks such a k); each shard draws its own keys
    (`fold_in` of the shard index) and the shards agree through collectives: gradients and
    metrics are averaged, the normalisers see every shard's data. Same algorithm as k = 1,
    with other random draws. What the env must offer is checked before (`run.validate`).
    """
    train, agent, spec = config.train, config.agent, env.observation_spec
    steps, future_p = agent.family.update_order, her_probability(train.her_k)
    shards = Shards(env_shards)
    learner = make_learner(env, config, shards)
    networks, optimizers, update = learner.networks, learner.optimizers, learner.update
    # observation noise (paper Eq. 9) on these proprio features; none: the noise code is not traced
    noise_map = noise.noise_map(spec, noise.parse_segments(train.noise_segments), train.noise_variant)
    noisy = noise_map.indices
    if len(noisy) and env_shards > 1:  # σ is a quantile of the whole buffer, which no shard holds
        raise ConfigError(f"--noise-segments {train.noise_segments!r} runs with 1 env shard only "
                          f"(here {env_shards}; `device_layout` gives 1)")
    n_envs, n_eval = train.num_envs // env_shards, train.eval_envs // env_shards
    # the evaluation runs in chunks of the cycles' width inside the cycles' scan, through the same traced env
    # step, where they roll out exactly n_eval episodes; otherwise (e.g. 128 of 2,048 envs) as a rollout of its
    # own, since padding it to the cycles' width would cost physics every epoch
    cycles, chunks = train.cycles_per_epoch, n_eval // n_envs if n_eval % n_envs == 0 else 0
    eval_width = n_envs if chunks else n_eval

    def policy(ts: TrainState, explore: bool | jax.Array) -> acting.Policy:
        return acting.make_policy(networks, config, acting.acting_params(ts, agent.family.acting_networks), explore)

    def eval_rows(chunk: jax.Array | int) -> jax.Array:
        """The evaluation episodes of chunk `chunk` [eval_width]: chunk·eval_width onwards."""
        return chunk * eval_width + jnp.arange(eval_width)

    def observer(ts: TrainState, evaluating: bool | jax.Array, chunk: jax.Array | int) -> acting.Observer | None:
        """What the agent sees of an observation: with noise on the `noisy` features, if any. A cycle draws
        the noise of its n_envs episodes; an evaluation chunk takes its rows of the draw for all n_eval, as
        one rollout of them (`acting.evaluate`) draws it."""
        if not len(noisy):
            return None

        def observe(obs: dict, key: jax.Array) -> dict:
            seen = branch(evaluating, lambda: noise.draw(ts.noise, noise_map, key, (n_eval,))[eval_rows(chunk)],
                          lambda: noise.draw(ts.noise, noise_map, key, (n_envs,)))
            return noise.noised(noise_map, obs, seen)

        return observe

    def init(key: jax.Array) -> TrainState:
        key_params, key_state = jax.random.split(key)
        params = networks.init(key_params)
        episode = replay.episode_template(env, agent.uses_image, len(noisy))
        return TrainState(
            params=params,
            target_params=params,
            opt_state={step.name: optimizers[step.name].init(step.trained(params)) for step in steps},
            proprio_norm=normalizer.init(spec.proprio_size),
            goal_norm=normalizer.init(spec.goal_size),
            buffer=replay.init(train.buffer_episodes // env_shards, episode),
            key=key_state,
            eval_key=jax.random.split(key_state)[1],  # replaced by each epoch's evaluation key
            noise=noise.init(train.obs_noise, len(noisy)) if len(noisy) else None,
            env_steps=jnp.zeros((), jnp.int32),
            updates=jnp.zeros((), jnp.int32),
            epoch=jnp.zeros((), jnp.int32),
        )

    def cycle_start(draws: Draws, buffer: replay.ReplayState, chunk: jax.Array) -> tuple[Draws, Phase]:
        """A cycle's keys and the starts of its n_envs exploring episodes (with `exploration_starts`); σ of
        the observation noise from the clean history collected so far, before every rollout."""
        if len(noisy):
            draws = draws._replace(noise=noise.refresh(draws.noise, buffer.episodes["clean"], buffer.size))
        key, key_rollout, key_updates, key_goals = jax.random.split(draws.key, 4)
        key_start, key_steps = jax.random.split(shards.own_key(key_rollout))
        starts = acting.draw_starts(key_start, n_envs, train.exploration_starts)
        return draws._replace(key=key), Phase(starts, key_steps, key_updates, key_goals)

    def eval_start(draws: Draws, buffer: replay.ReplayState, chunk: jax.Array | int) -> tuple[Draws, Phase]:
        """The epoch's evaluation key (drawn by chunk 0, after the last cycle) and the starts of chunk
        `chunk`'s episodes, from `env.reset` as one rollout of all n_eval (`acting.evaluate`) draws them."""
        key, key_eval = jax.random.split(draws.key)
        first = chunk == 0
        draws = draws._replace(key=jnp.where(first, key, draws.key),
                               eval_key=jnp.where(first, key_eval, draws.eval_key))
        key_eval = shards.own_key(draws.eval_key)
        starts = acting.Starts(jax.random.split(jax.random.split(key_eval)[0], n_eval)[eval_rows(chunk)])
        if train.exploration_starts > 0 and chunks:  # in the cycles' scan: shaped as theirs, none picked
            starts = starts._replace(eased=starts.reset, pick=jnp.zeros((n_envs,), bool))
        return draws, Phase(starts, key_eval, key_eval, key_eval)

    def insert(buffer: replay.ReplayState, episodes: dict, evaluating: bool | jax.Array) -> replay.ReplayState:
        """`replay.insert` of a cycle's episodes. An evaluation chunk writes back what the slots hold and does
        not advance, so that the buffer is updated in place in every phase, outside `lax.cond` (whose outputs
        XLA would copy: hundreds of MB of images)."""
        if isinstance(evaluating, bool):
            return buffer if evaluating else replay.insert(buffer, episodes)
        held = jax.tree.map(lambda b: jax.lax.dynamic_slice_in_dim(b, buffer.position, n_envs), buffer.episodes)
        kept = jax.tree.map(lambda e, h: jnp.where(evaluating, h, e.astype(h.dtype)), episodes, held)
        written = replay.insert(buffer, kept)
        return written.replace(position=jnp.where(evaluating, buffer.position, written.position),
                               size=jnp.where(evaluating, buffer.size, written.size))

    def learn(ts: TrainState, phase: Phase, final: Any, episodes: dict) -> tuple[TrainState, dict]:
        """A cycle's learning from its rollout (its episodes already inserted): update the normalisers, then
        `updates_per_cycle` gradient steps. The state comes back without its buffer, which no update changes."""
        # the goal normaliser sees the goals the critic will see: desired and HER-relabelled
        with jax.named_scope(NORMALISER_SCOPE):
            goals = replay.her_goals(episodes, shards.own_key(phase.key_goals), n_envs * env.episode_length,
                                     future_p)
            ts = ts.replace(
                proprio_norm=normalizer.update(ts.proprio_norm, shards.everyone(episodes["proprio"])),
                goal_norm=normalizer.update(ts.goal_norm, shards.everyone(goals)),
                env_steps=ts.env_steps + train.num_envs * env.episode_length,
            )
        ts, metrics = jax.lax.scan(update, ts, jax.random.split(phase.key_updates, train.updates_per_cycle))
        success = final.metrics["success"]
        kinds = {} if phase.starts.pick is None else start_kinds(phase.starts.pick)
        counted = {f"{kind}{part}": shards.average(value) for kind, mask in kinds.items()
                   for part, value in ((HITS, (success * mask).sum()), (COUNT, mask.sum().astype(jnp.float32)))}
        return ts.replace(buffer=None), {**shards.average(jax.tree.map(jnp.mean, metrics)), **counted,
                                         "train_success": shards.average(success.mean())}

    learned = jax.jit(learn)  # one trace serves the program and the shapes of its metrics (`skip`)

    def skip(ts: TrainState, *rollout) -> tuple[TrainState, dict]:
        """An evaluation chunk's `learn`: nothing learned, zero metrics."""
        shapes = jax.eval_shape(learned, ts, *rollout)[1]
        return ts.replace(buffer=None), jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)

    def phase(ts: TrainState, chunk: jax.Array | int, evaluating: bool | jax.Array) -> tuple:
        """(state, phase, final states, records) of one phase: a cycle's exploring rollout of n_envs
        episodes, or evaluation chunk `chunk`'s greedy one of eval_width episodes."""
        draws = Draws(ts.key, ts.eval_key, ts.noise)  # what a phase's start changes: not the whole state
        draws, plan = branch(evaluating, eval_start, cycle_start, draws, ts.buffer, chunk)
        ts = ts.replace(key=draws.key, eval_key=draws.eval_key, noise=draws.noise)
        explore = not evaluating if isinstance(evaluating, bool) else jnp.logical_not(evaluating)
        final, records = acting.rollout(
            env, policy(ts, explore), plan.key, states=acting.states_at(env, plan.starts),
            observe=observer(ts, evaluating, chunk),
            record=lambda step: (step.obs, step.action, step.state.obs["proprio"][..., noisy]),
        )
        return ts, plan, final, records

    def step(ts: TrainState, index: jax.Array) -> tuple[TrainState, tuple]:
        """Phase `index` of the epoch's scan: cycle `index`, or from `cycles_per_epoch` on, evaluation chunk
        index - cycles_per_epoch (where `chunks` puts the evaluation in the scan). Both roll out n_envs episodes
        through the one traced env step, exploring or greedy; a cycle then learns from its episodes, an
        evaluation chunk keeps their success."""
        evaluating = index >= cycles if chunks else False
        ts, plan, final, records = phase(ts, index - cycles, evaluating)
        last = final.obs if not len(noisy) else noise.observe(ts.noise, noise_map, final.obs,
                                                               jax.random.fold_in(plan.key, 2))
        with jax.named_scope(REPLAY_SCOPE):
            episodes = replay.to_episodes(records, final.obs, last, noisy, agent.uses_image)
            buffer = insert(ts.buffer, episodes, evaluating)
        ts, metrics = branch(evaluating, skip, learned, ts.replace(buffer=buffer), plan, final, episodes)
        ts = ts.replace(buffer=buffer)
        return ts, (metrics, final.metrics["success"], final.info["goal"])

    def epoch(ts: TrainState) -> tuple[TrainState, dict[str, jax.Array]]:
        """`cycles_per_epoch` cycles, then `eval_envs` deterministic evaluation episodes: in the cycles' scan
        (`chunks` of n_envs) or after it."""
        ts, (metrics, success, goals) = jax.lax.scan(step, ts, jnp.arange(cycles + chunks))
        if chunks:
            success, goals = success[cycles:].reshape(-1), goals[cycles:].reshape(-1, goals.shape[-1])
        else:
            with jax.named_scope(EVALUATION_SCOPE):
                ts, _, final, _ = phase(ts, 0, True)
            success, goals = final.metrics["success"], final.info["goal"]
        ts = ts.replace(epoch=ts.epoch + 1)
        metrics = {**jax.tree.map(lambda m: m[:cycles].mean(), metrics), "eval_success": shards.average(success.mean()),
                   "env_steps": ts.env_steps}
        for kind in (k for k in list(metrics) if k.endswith(HITS)):  # the cycles' successes of a start kind
            name = kind.removesuffix(HITS)
            metrics[name] = metrics.pop(kind) / jnp.maximum(metrics.pop(name + COUNT), 1e-9)
        for name, mask in env.goal_subsets(goals).items():  # e.g. nicol_lift's air goals: success among them
            hits, count = shards.average((success * mask).sum()), shards.average(mask.sum().astype(jnp.float32))
            metrics[f"eval_success_{name}"] = hits / jnp.maximum(count, 1.0)
        return ts, metrics

    return init, epoch
