"""A checkpoint whose Adam moments were saved per parameter array (before `train.optimizer` raveled each network
group's parameters into one vector) restores with its moments raveled as `optax.flatten` ravels them."""

import os

import jax
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

import envs_mjx
from bidal_jax import train
from bidal_jax.run import checkpoint, loop
from experiments.cli import resolve

SEEDS = 2


def _per_parameter(lr: float, grad_clip: float) -> optax.GradientTransformation:
    """The optimiser as it was: one Adam state per parameter array."""
    return optax.chain(optax.clip_by_global_norm(grad_clip), optax.adam(lr))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """(config, env, the state saved with moments per parameter array, each moment leaf distinct numbers)."""
    run_dir = str(tmp_path_factory.mktemp("moments") / "run")
    config = resolve({"env": "planar_reach", "agent": "proprio_baseline", "seeds": SEEDS, "num_envs": 4,
                      "buffer_episodes": 8, "eval_envs": 4, "run_dir": run_dir})
    env = envs_mjx.make("planar_reach", render=False)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(train, "optimizer", _per_parameter)
        init, _ = train.make_train(env, config)
        state = jax.vmap(init)(jax.random.split(jax.random.PRNGKey(0), SEEDS))
    leaves, tree = jax.tree.flatten(state.opt_state)
    numbered = [np.arange(x.size, dtype=x.dtype).reshape(x.shape) + 1000 * i
                if np.issubdtype(x.dtype, np.floating) else np.asarray(x) for i, x in enumerate(leaves)]
    state = state.replace(opt_state=jax.tree.unflatten(tree, numbered))
    manager = checkpoint.manager(os.path.join(run_dir, "checkpoints"))
    checkpoint.save(manager, 1, state, config.to_dict(), 0.0)
    manager.close()
    return config, env, state


def test_moments_per_parameter_restore_raveled_in_the_parameters_order(saved):
    config, env, old = saved
    restored, epoch = loop.restore_state(env, config)
    assert epoch == 1
    for name, old_state in old.opt_state.items():
        old_adam, new_adam = old_state[1][0], restored.opt_state[name][1][0]
        assert isinstance(old_adam.mu, dict) and np.ndim(new_adam.mu) == 2  # saved per parameter, restored raveled
        np.testing.assert_array_equal(np.asarray(new_adam.count), np.asarray(old_adam.count))
        for moment in ("mu", "nu"):
            got = np.asarray(getattr(new_adam, moment))
            for seed in range(SEEDS):
                want, _ = ravel_pytree(jax.tree.map(lambda x, s=seed: x[s], getattr(old_adam, moment)))
                np.testing.assert_array_equal(got[seed], np.asarray(want), err_msg=f"{name} {moment} seed {seed}")
    np.testing.assert_array_equal(np.asarray(jax.tree.leaves(restored.params)[0]),
                                  np.asarray(jax.tree.leaves(old.params)[0]))


def test_the_raveled_moments_take_the_step_the_per_parameter_ones_took(saved):
    """One Adam step of each update step's group from the restored (raveled) state and from the saved one: the
    same updates, to rounding."""
    config, env, old = saved
    restored, _ = loop.restore_state(env, config)
    seed0 = lambda tree: jax.tree.map(lambda x: x[0], tree)  # noqa: E731
    for step in config.agent.family.update_order:
        trained = step.trained(seed0(old.params))
        grads = jax.tree.map(lambda x: np.full(x.shape, 0.5, x.dtype), trained)
        lr, clip = step.learning_rate(config.train), config.train.grad_clip
        want, _ = _per_parameter(lr, clip).update(grads, seed0(old.opt_state[step.name]), trained)
        got, _ = train.optimizer(lr, clip).update(grads, seed0(restored.opt_state[step.name]), trained)
        for a, b in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-8, err_msg=step.name)
