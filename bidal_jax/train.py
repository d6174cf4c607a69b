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
import functools
from typing import Any, Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from bidal_jax import acting, noise, normalizer, replay, schedule
from bidal_jax.config import Config, ConfigError
from bidal_jax.schedule import Draws, Phase, branch

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


HITS, COUNT = "_hits", "_count"  # a cycle's successes and episodes of a start kind, summed into its rate by `epoch`


def start_kinds(pick: jax.Array) -> dict[str, jax.Array]:
    """The training episodes of each start kind, as masks [n] of `acting.Starts.pick`: "train_success_held" begun by
    `env.exploration_reset` (nicol_lift: the cube in the hand, HER's pick-and-place protocol) and
    "train_success_table" by `env.reset`, so that a run shows how far the held starts alone carry its success."""
    return {"train_success_held": pick, "train_success_table": jnp.logical_not(pick)}


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


def initial_state(env, config: Config, learner: Learner, n_noisy: int, env_shards: int, key: jax.Array) -> TrainState:
    """A run's state before its first epoch: the learner's initial parameters (the targets equal to them) and
    optimiser states, empty normalisers and an empty buffer of one env shard's share of `buffer_episodes`, whose
    episodes keep the clean values of `n_noisy` noisy proprio features."""
    train, spec = config.train, env.observation_spec
    key_params, key_state = jax.random.split(key)
    params = learner.networks.init(key_params)
    episode = replay.episode_template(env, config.agent.uses_image, n_noisy)
    return TrainState(
        params=params, target_params=params,
        opt_state={step.name: learner.optimizers[step.name].init(step.trained(params))
                   for step in config.agent.family.update_order},
        proprio_norm=normalizer.init(spec.proprio_size), goal_norm=normalizer.init(spec.goal_size),
        buffer=replay.init(train.buffer_episodes // env_shards, episode),
        key=key_state, eval_key=jax.random.split(key_state)[1],  # replaced by each epoch's evaluation key
        noise=noise.init(train.obs_noise, n_noisy) if n_noisy else None,
        env_steps=jnp.zeros((), jnp.int32), updates=jnp.zeros((), jnp.int32), epoch=jnp.zeros((), jnp.int32),
    )


def cycle_metrics(shards: Shards, metrics: dict, success: jax.Array, pick: jax.Array | None) -> dict[str, jax.Array]:
    """A cycle's metrics: its updates' means [updates_per_cycle] and its episodes' success [n], overall and (with
    exploration starts `pick`) as the hits and episodes of each start kind, that `epoch_metrics` makes a rate."""
    kinds = {} if pick is None else start_kinds(pick)
    counted = {f"{kind}{part}": shards.average(value) for kind, mask in kinds.items()
               for part, value in ((HITS, (success * mask).sum()), (COUNT, mask.sum().astype(jnp.float32)))}
    return {**shards.average(jax.tree.map(jnp.mean, metrics)), **counted,
            "train_success": shards.average(success.mean())}


def epoch_metrics(env, shards: Shards, cycles: int, metrics: dict, success: jax.Array, goals: jax.Array,
                  env_steps: jax.Array) -> dict[str, jax.Array]:
    """An epoch's metrics: its cycles' means (a start kind's success rate from its hits and episodes), and the
    evaluation's success [n_eval] overall and among each of `env.goal_subsets` of its goals [n_eval, G]."""
    metrics = {**jax.tree.map(lambda m: m[:cycles].mean(), metrics), "eval_success": shards.average(success.mean()),
               "env_steps": env_steps}
    for kind in (k for k in list(metrics) if k.endswith(HITS)):  # the cycles' successes of a start kind
        name = kind.removesuffix(HITS)
        metrics[name] = metrics.pop(kind) / jnp.maximum(metrics.pop(name + COUNT), 1e-9)
    for name, mask in env.goal_subsets(goals).items():  # e.g. nicol_lift's air goals: success among them
        hits, count = shards.average((success * mask).sum()), shards.average(mask.sum().astype(jnp.float32))
        metrics[f"eval_success_{name}"] = hits / jnp.maximum(count, 1.0)
    return metrics


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
    shards, future_p = Shards(env_shards), her_probability(train.her_k)
    learner = make_learner(env, config, shards)
    # observation noise (paper Eq. 9) on these proprio features; none: the noise code is not traced
    noise_map = noise.noise_map(spec, noise.parse_segments(train.noise_segments), train.noise_variant)
    noisy = noise_map.indices
    if len(noisy) and env_shards > 1:  # σ is a quantile of the whole buffer, which no shard holds
        raise ConfigError(f"--noise-segments {train.noise_segments!r} runs with 1 env shard only "
                          f"(here {env_shards}; `device_layout` gives 1)")
    phases = schedule.Schedule(train.cycles_per_epoch, train.num_envs // env_shards, train.eval_envs // env_shards,
                               train.exploration_starts)
    n_envs, cycles = phases.n_envs, phases.cycles

    init = functools.partial(initial_state, env, config, learner, len(noisy), env_shards)

    def cycle_start(draws: Draws, buffer: replay.ReplayState, chunk: jax.Array) -> tuple[Draws, Phase]:
        """A cycle's keys and the starts of its n_envs exploring episodes (with `exploration_starts`); σ of
        the observation noise from the clean history collected so far, before every rollout."""
        if len(noisy):
            draws = draws._replace(noise=noise.refresh(draws.noise, buffer.episodes["clean"], buffer.size))
        key, key_rollout, key_updates, key_goals = jax.random.split(draws.key, 4)
        key_start, key_steps = jax.random.split(shards.own_key(key_rollout))
        starts = acting.draw_starts(key_start, n_envs, train.exploration_starts)
        return draws._replace(key=key), Phase(starts, key_steps, key_updates, key_goals)

    def rollout(ts: TrainState, chunk: jax.Array | int, evaluating: schedule.Flag) -> tuple:
        """(state, phase, final states, records) of a cycle's exploring rollout of n_envs episodes, or of evaluation
        chunk `chunk`'s greedy one; the agent sees noise on the `noisy` features drawn for the phase's episodes."""
        draws = Draws(ts.key, ts.eval_key, ts.noise)  # what a phase's start changes: not the whole state
        draws, phase = branch(evaluating, lambda d, _, c: phases.evaluation_start(d, c, shards.own_key),
                              cycle_start, draws, ts.buffer, chunk)
        ts = ts.replace(key=draws.key, eval_key=draws.eval_key, noise=draws.noise)
        explore = not evaluating if isinstance(evaluating, bool) else jnp.logical_not(evaluating)
        acting_params = acting.acting_params(ts, agent.family.acting_networks)
        policy = acting.make_policy(learner.networks, config, acting_params, explore)

        def observe(obs: dict, key: jax.Array) -> dict:
            seen = phases.per_episode(evaluating, chunk, lambda n: noise.draw(ts.noise, noise_map, key, (n,)))
            return noise.noised(noise_map, obs, seen)

        final, records = acting.rollout(
            env, policy, phase.key, states=acting.states_at(env, phase.starts), observe=observe if len(noisy) else None,
            record=lambda step: (step.obs, step.action, step.state.obs["proprio"][..., noisy]),
        )
        return ts, phase, final, records

    def insert(ts: TrainState, phase: Phase, final: Any, records: Any, evaluating: schedule.Flag) -> tuple:
        """(buffer, episodes): the phase's episodes inserted into the buffer (`Schedule.insert`)."""
        last = final.obs if not len(noisy) else noise.observe(ts.noise, noise_map, final.obs,
                                                               jax.random.fold_in(phase.key, 2))
        with jax.named_scope(REPLAY_SCOPE):
            episodes = replay.to_episodes(records, final.obs, last, noisy, agent.uses_image)
            return phases.insert(ts.buffer, episodes, evaluating), episodes

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
        ts, metrics = jax.lax.scan(learner.update, ts, jax.random.split(phase.key_updates, train.updates_per_cycle))
        return ts.replace(buffer=None), cycle_metrics(shards, metrics, final.metrics["success"], phase.starts.pick)

    learned, skip = schedule.learn_or_skip(learn)

    def step(ts: TrainState, index: jax.Array) -> tuple[TrainState, tuple]:
        """Phase `index` of the epoch's scan, cycle `index` or evaluation chunk index - cycles (`Schedule`): a
        rollout of n_envs episodes through the one traced env step, their insert, then a cycle's learning."""
        evaluating = phases.evaluating(index)
        ts, phase, final, records = rollout(ts, index - cycles, evaluating)
        buffer, episodes = insert(ts, phase, final, records, evaluating)
        ts, metrics = branch(evaluating, skip, learned, ts.replace(buffer=buffer), phase, final, episodes)
        return ts.replace(buffer=buffer), (metrics, final.metrics["success"], final.info["goal"])

    def epoch(ts: TrainState) -> tuple[TrainState, dict[str, jax.Array]]:
        """`cycles_per_epoch` cycles, then `eval_envs` deterministic evaluation episodes: in the cycles' scan
        (`chunks` of n_envs) or after it."""
        ts, (metrics, success, goals) = jax.lax.scan(step, ts, jnp.arange(cycles + phases.chunks))
        if phases.chunks:
            success, goals = phases.evaluated(success, goals)
        else:
            with jax.named_scope(EVALUATION_SCOPE):
                ts, _, final, _ = rollout(ts, 0, True)
            success, goals = final.metrics["success"], final.info["goal"]
        ts = ts.replace(epoch=ts.epoch + 1)
        return ts, epoch_metrics(env, shards, cycles, metrics, success, goals, ts.env_steps)

    return init, epoch
