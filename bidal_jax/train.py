"""The training loop as pure functions: `make_train(env, agent, ...) -> (init, epoch)`.

`epoch` is ONE jit-able function: a `lax.scan` over cycles of (vectorised rollout of all
parallel envs with exploration, buffer insert, normaliser update, n gradient updates,
target update after every gradient step), then deterministic evaluation rollouts. Both
rollouts are `acting.rollout` with `acting.make_policy`. Seeds are a `vmap` over
`init`/`epoch`, sharded over devices (see `make_seeded`). Python only runs the outer loop.

Devices left over by the seeds split each seed's envs (`env_shards`, see `device_layout`): each
shard steps its share of the envs, keeps its share of the replay buffer, draws its share of
each batch and averages its gradients with the other shards' (`lax.pmean`), so the shards
hold identical parameters, as data-parallel training does.
"""

from __future__ import annotations

import functools
import math
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from bidal_jax import acting, noise, normalizer, replay
from bidal_jax.config import AgentSpec, NetworkConfig, TrainConfig
from bidal_jax.losses import make_losses
from bidal_jax.networks import make_networks
from bidal_jax.run.validate import ConfigError, check_env_support

SEED_AXIS, ENV_AXIS = "seeds", "envs"  # the device mesh's axes (`make_seeded`)


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


def _optimizer(lr: float, grad_clip: float) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(grad_clip), optax.adam(lr))


def polyak(target: Any, online: Any, tau: float) -> Any:
    """target ← (1 - τ) target + τ online."""
    return jax.tree.map(lambda t, o: (1.0 - tau) * t + tau * o, target, online)


def make_train(env, agent: AgentSpec, net_config: NetworkConfig, config: TrainConfig, env_shards: int = 1):
    """Build `init(key) -> TrainState` and `epoch(TrainState) -> (TrainState, metrics)`.

    With `env_shards` k > 1 the functions are one shard's part of a `shard_map` over the mesh
    axis `ENV_AXIS` (`make_seeded`): k divides the envs, evaluation envs, batch and buffer
    (`device_layout` picks such a k); each shard draws its own keys (`fold_in` of the shard index)
    and the shards agree through collectives: gradients and metrics are averaged, the
    normalisers see every shard's data. Same algorithm as k = 1, with other random draws.
    """
    check_env_support(config, env)
    spec = env.observation_spec
    horizon = env.episode_length
    networks = make_networks(agent, net_config, spec.proprio_size, spec.goal_size, env.action_size, spec.image_shape)
    losses = make_losses(networks, config, agent.bidal)
    rep_opt = _optimizer(config.critic_lr, config.grad_clip)
    actor_opt = _optimizer(config.actor_lr, config.grad_clip)
    future_p = 1.0 - 1.0 / (1.0 + config.her_k)
    rep_keys = ("encoder", "critic", "forward", "inverse")
    # observation noise (paper Eq. 9) on these proprio features; none: the noise code is not traced
    noisy = noise.feature_indices(spec.proprio_segments, noise.parse_segments(config.noise_segments))
    if len(noisy) and env_shards > 1:  # σ is a quantile of the whole buffer, which no shard holds
        raise ConfigError(f"--noise-segments {config.noise_segments!r} runs with 1 env shard only "
                          f"(here {env_shards}; `device_layout` gives 1)")
    n_envs, n_eval, n_batch = (n // env_shards for n in (config.num_envs, config.eval_envs, config.batch_size))

    def own_key(key):
        """This shard's key: `key` itself when unsharded."""
        return key if env_shards == 1 else jax.random.fold_in(key, jax.lax.axis_index(ENV_AXIS))

    def everyone(x):
        """x [n, ...] of every shard, concatenated: [k·n, ...]."""
        return x if env_shards == 1 else jax.lax.all_gather(x, ENV_AXIS, tiled=True)

    def average(tree):
        """The mean over shards of a pytree (gradients, metrics)."""
        return tree if env_shards == 1 else jax.lax.pmean(tree, ENV_AXIS)

    def rep_params(params):
        return {k: v for k, v in params.items() if k in rep_keys}

    def normalize_proprio(ts, x):
        return normalizer.normalize(ts.proprio_norm, x, config.clip_obs)

    def normalize_goal(ts, x):
        return normalizer.normalize(ts.goal_norm, x, config.clip_obs)

    def policy(ts: TrainState, explore: bool) -> acting.Policy:
        return acting.make_policy(networks, agent, config, acting.acting_params(ts), explore)

    def observer(ts: TrainState) -> acting.Observer | None:
        """What the agent sees of an observation: with noise on the `noisy` features, if any."""
        if not len(noisy):
            return None
        return lambda obs, key: noise.observe(ts.noise, noisy, obs, key)

    def collect(ts: TrainState, key: jax.Array):
        """One exploring episode in each of `num_envs` envs, as replay episodes (observations as
        the agent saw them; with noise, also the clean noised features); train success."""
        key_start, key_steps = jax.random.split(key)
        states = acting.start_states(env, key_start, n_envs, config.exploration_starts)
        observe = observer(ts)
        final, (obs, actions, clean) = acting.rollout(
            env, policy(ts, explore=True), key_steps, states=states, observe=observe,
            record=lambda step: (step.obs, step.action, step.state.obs["proprio"][..., noisy]),
        )
        last = final.obs if observe is None else observe(final.obs, jax.random.fold_in(key_steps, 2))

        def with_final(x, last):  # [T, N, ...] + [N, ...] -> [N, T+1, ...]
            return jnp.swapaxes(jnp.concatenate([x, last[None]]), 0, 1)

        episodes = {
            "proprio": with_final(obs["proprio"], last["proprio"]),
            "achieved_goal": with_final(obs["achieved_goal"], last["achieved_goal"]),
            "desired_goal": final.obs["desired_goal"],
            "action": jnp.swapaxes(actions, 0, 1),
        }
        if agent.uses_image:
            episodes["image"] = with_final(obs["image"], last["image"])
        if len(noisy):
            episodes["clean"] = with_final(clean, final.obs["proprio"][..., noisy])
        return episodes, average(final.metrics["success"].mean())

    example_episode = {
        "proprio": jnp.zeros((horizon + 1, spec.proprio_size), jnp.float32),
        "achieved_goal": jnp.zeros((horizon + 1, spec.goal_size), jnp.float32),
        "desired_goal": jnp.zeros((spec.goal_size,), jnp.float32),
        "action": jnp.zeros((horizon, env.action_size), jnp.float32),
    }
    if agent.uses_image:
        example_episode["image"] = jnp.zeros((horizon + 1, *spec.image_shape), jnp.uint8)
    if len(noisy):
        example_episode["clean"] = jnp.zeros((horizon + 1, len(noisy)), jnp.float32)

    def init(key: jax.Array) -> TrainState:
        key_params, key_state = jax.random.split(key)
        params = networks.init(key_params)
        return TrainState(
            params=params,
            target_params=params,
            opt_state={"representation": rep_opt.init(rep_params(params)), "actor": actor_opt.init(params["actor"])},
            proprio_norm=normalizer.init(spec.proprio_size),
            goal_norm=normalizer.init(spec.goal_size),
            buffer=replay.init(config.buffer_episodes // env_shards, example_episode),
            key=key_state,
            eval_key=jax.random.split(key_state)[1],  # replaced by each epoch's evaluation key
            noise=noise.init(config.obs_noise, len(noisy)) if len(noisy) else None,
            env_steps=jnp.zeros((), jnp.int32),
            updates=jnp.zeros((), jnp.int32),
            epoch=jnp.zeros((), jnp.int32),
        )

    def update(ts: TrainState, key: jax.Array):
        """One gradient step of the representation group (encoder, critic, f, g) and the actor."""
        batch = replay.sample(ts.buffer, own_key(key), n_batch, future_p, env.compute_reward)
        batch = {
            **batch,
            "proprio": normalize_proprio(ts, batch["proprio"]),
            "next_proprio": normalize_proprio(ts, batch["next_proprio"]),
            "goal": normalize_goal(ts, batch["goal"]),
        }
        rp = rep_params(ts.params)
        grads, aux = jax.grad(losses.representation, has_aux=True)(rp, ts.target_params, batch)
        grads = average(grads)
        updates, rep_state = rep_opt.update(grads, ts.opt_state["representation"], rp)
        params = {**ts.params, **optax.apply_updates(rp, updates)}
        actor_grads, actor_aux = jax.grad(losses.actor, has_aux=True)(params["actor"], params, {**batch, "phi": aux.pop("phi")})
        actor_grads = average(actor_grads)
        actor_updates, actor_state = actor_opt.update(actor_grads, ts.opt_state["actor"], params["actor"])
        params["actor"] = optax.apply_updates(params["actor"], actor_updates)
        ts = ts.replace(
            params=params,
            target_params=polyak(ts.target_params, params, config.tau),
            opt_state={"representation": rep_state, "actor": actor_state},
            updates=ts.updates + 1,
        )
        return ts, {**aux, **actor_aux}

    def cycle(ts: TrainState, _):
        if len(noisy):  # σ from the clean history collected so far, before every rollout
            ts = ts.replace(noise=noise.refresh(ts.noise, ts.buffer.episodes["clean"], ts.buffer.size))
        key, key_rollout, key_updates, key_goals = jax.random.split(ts.key, 4)
        episodes, train_success = collect(ts, own_key(key_rollout))
        # the goal normaliser sees the goals the critic will see: desired and HER-relabelled
        goals = replay.her_goals(episodes, own_key(key_goals), n_envs * horizon, future_p)
        ts = ts.replace(
            key=key,
            buffer=replay.insert(ts.buffer, episodes),
            proprio_norm=normalizer.update(ts.proprio_norm, everyone(episodes["proprio"])),
            goal_norm=normalizer.update(ts.goal_norm, everyone(goals)),
            env_steps=ts.env_steps + config.num_envs * horizon,
        )
        ts, metrics = jax.lax.scan(update, ts, jax.random.split(key_updates, config.updates_per_cycle))
        return ts, {**average(jax.tree.map(jnp.mean, metrics)), "train_success": train_success}

    def epoch(ts: TrainState) -> tuple[TrainState, dict[str, jax.Array]]:
        ts, metrics = jax.lax.scan(cycle, ts, None, length=config.cycles_per_epoch)
        key, key_eval = jax.random.split(ts.key)
        success = acting.evaluate(env, policy(ts, explore=False), own_key(key_eval), n_eval, observe=observer(ts))
        eval_success = average(success.mean())
        ts = ts.replace(key=key, eval_key=key_eval, epoch=ts.epoch + 1)
        metrics = {**jax.tree.map(jnp.mean, metrics), "eval_success": eval_success, "env_steps": ts.env_steps}
        return ts, metrics

    return init, epoch


def seed_devices(seeds: int, devices: Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The devices that `seeds` vmapped seeds are spread over: of each process's `devices` (default:
    all, of every process), as many as divide that process's share of the seeds evenly (one process
    with 4 GPUs: 8 seeds on 4, 6 on 2, 1 seed on 1; two with 2 devices each: 4 seeds on 2 + 2).
    Raises ConfigError when the processes cannot hold equal shares."""
    owned = _by_process(devices)
    if seeds % len(owned):
        raise ConfigError(f"--seeds {seeds}: must be a multiple of the {len(owned)} processes (each holds as many seeds)")
    per_process = math.gcd(seeds // len(owned), min(len(own) for own in owned))
    return [d for own in owned for d in own[:per_process]]


def _by_process(devices: Sequence[jax.Device] | None) -> list[list[jax.Device]]:
    """`devices` (default: all, of every process) grouped by process, in process order."""
    devices = list(jax.devices() if devices is None else devices)
    return [[d for d in devices if d.process_index == p] for p in sorted({d.process_index for d in devices})]


def device_layout(
    seeds: int, config: TrainConfig, max_shards: int = 1, devices: Sequence[jax.Device] | None = None
) -> tuple[list, int]:
    """(the devices of a run, its env shards k): `seed_devices` hold the seeds, and each seed
    device's process lends it, of the devices left over, the most (k - 1, k ≤ `max_shards`)
    such that k divides the envs, evaluation envs and batch (k = 1 with observation noise, see
    `make_train`). The devices come seed device by seed device, each followed by its shards'
    others. One process with 4 devices, 16 envs, `max_shards` 4: 1 seed on 4 × 4 shards,
    2 seeds on 2 × 2, 4 on 4 × 1; with 6 envs, 1 seed on 2 × 2."""
    owned = _by_process(devices)
    per_process = len(seed_devices(seeds, devices)) // len(owned)
    spare = min(min(len(own) for own in owned) // per_process, max_shards)
    divisor = 1 if config.noise_segments else math.gcd(config.num_envs, config.eval_envs, config.batch_size)
    shards = max(k for k in range(1, spare + 1) if divisor % k == 0)
    return [d for own in owned for d in own[:per_process * shards]], shards


def _mesh(devices: Sequence[jax.Device], shards: int) -> Mesh:
    return Mesh(np.array(devices).reshape(-1, shards), (SEED_AXIS, ENV_AXIS))


def _state_specs() -> TrainState:
    """The mesh axes of a TrainState[S]'s leaves (a pytree prefix): the seed axis everywhere, and
    the replay buffer's episodes also split over the env shards (each shard keeps its own)."""
    seed = P(SEED_AXIS)
    return TrainState(
        params=seed, target_params=seed, opt_state=seed, proprio_norm=seed, goal_norm=seed,
        buffer=replay.ReplayState(episodes=P(SEED_AXIS, ENV_AXIS), position=seed, size=seed),
        key=seed, eval_key=seed, noise=seed, env_steps=seed, updates=seed, epoch=seed,
    )


def seed_sharding(devices: Sequence[jax.Device], shards: int = 1) -> Any:
    """Where a TrainState[S] (or any seed-leading pytree, with `shards` 1) lives on `devices`, for
    `jax.device_put`: with `shards` 1, every leaf's leading (seed) axis split over a 1-D mesh
    named "seeds"; else the state's leaves on the [seeds, envs] mesh (`_state_specs`)."""
    if shards == 1:
        return NamedSharding(Mesh(np.array(devices), (SEED_AXIS,)), P(SEED_AXIS))
    mesh = _mesh(devices, shards)
    return jax.tree.map(lambda spec: NamedSharding(mesh, spec), _state_specs(), is_leaf=lambda x: isinstance(x, P))


def make_seeded(init: Callable, epoch: Callable, devices: Sequence[jax.Device] | None = None, shards: int = 1):
    """Seeds as one vmapped, jitted program: `init(keys[S]) -> TrainState[S]`, `epoch`.

    The seed axis of the state, keys and metrics is sharded over `devices` (default: the
    first device) with `jax.sharding`: JAX's SPMD partitioner runs S / len(devices) seeds on
    each device in one program, with no communication between seeds. With `shards` k > 1
    (`init` and `epoch` from `make_train(..., env_shards=k)`), `devices` form a [S-shards, k]
    mesh and the program is a `shard_map` over it: each device runs its seeds' share of the envs.
    """
    devices = jax.devices()[:1] if devices is None else devices
    if shards == 1:
        sharding = seed_sharding(devices)
        return (
            jax.jit(jax.vmap(init), in_shardings=sharding, out_shardings=sharding),
            jax.jit(jax.vmap(epoch), in_shardings=sharding, out_shardings=sharding, donate_argnums=0),
        )
    # no vma type check: MJX's loops carry env state that starts replicated (zeros) and becomes
    # shard-varying; what leaves the program replicated is averaged or gathered (`make_train`)
    mesh, specs = _mesh(devices, shards), _state_specs()
    sharded = functools.partial(jax.shard_map, mesh=mesh, check_vma=False)
    return (
        jax.jit(sharded(jax.vmap(init), in_specs=P(SEED_AXIS), out_specs=specs)),
        jax.jit(sharded(jax.vmap(epoch), in_specs=(specs,), out_specs=(specs, P(SEED_AXIS))), donate_argnums=0),
    )
