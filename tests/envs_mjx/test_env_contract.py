"""Env contract tests (docs/design.md, tier 2), shared by every registered environment."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting

# nicol_lift_reduced is nicol_lift with proprio segments dropped, and the ladder's nicol_slide_ee and
# nicol_slide_ee_obj are nicol_slide with only some kept: test_nicol.py checks them against nicol_lift and
# nicol_slide instead of compiling the whole contract again.
VARIANTS = ("nicol_lift_reduced", "nicol_slide_ee", "nicol_slide_ee_obj")
ENV_NAMES = tuple(name for name in envs_mjx.names() if name not in VARIANTS)


N_ENVS, N_STEPS = 10, 100  # 1,000 random steps, beyond the episode length too


@functools.lru_cache(maxsize=None)
def compiled(name):
    """One env per name with its jitted, vmapped reset and a random rollout from given states.

    Each env compiles its own rollout: even nicol_slide's and nicol_lift's, on one scene, lower to different
    programs (compared: one function more in nicol_lift's), so neither finds the other's in the cache."""
    env = envs_mjx.make(name)
    resets = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), N_ENVS))

    @jax.jit
    def random_rollout(states, key):
        # actions beyond [-1, 1] check the env's clipping
        return acting.rollout(
            env,
            acting.random_policy(env.action_size, scale=1.5),
            key,
            states=states,
            steps=N_STEPS,
            record=lambda step: (
                step.next_state.obs["proprio"],
                step.next_state.data.qpos,
                step.next_state.obs["achieved_goal"],
                step.next_state.obs["image"],
                step.next_state.data.geom_xpos,
                step.next_state.data.geom_xmat,
            ),
        )

    return env, resets, random_rollout


@functools.lru_cache(maxsize=None)
def rollout(name, seed):
    env, resets, random_rollout = compiled(name)
    return random_rollout(resets, jax.random.PRNGKey(seed))


@pytest.mark.parametrize("name", ENV_NAMES)
def test_reset_and_step_match_the_spec(name):
    env, resets, _ = compiled(name)
    final, _ = rollout(name, 1)
    for state in (resets, final):
        for key, (shape, dtype) in env.observation_spec.shapes().items():
            assert state.obs[key].shape == (N_ENVS, *shape), key
            assert state.obs[key].dtype == dtype, key
        assert state.obs["image"].shape == (N_ENVS, 42, 42, 1)
        assert state.reward.shape == (N_ENVS,) and state.reward.dtype == jnp.float32
    assert (np.asarray(resets.info["step"]) == 0).all() and (np.asarray(final.info["step"]) == N_STEPS).all()
    assert env.episode_length > 0 and env.action_size > 0


@pytest.mark.parametrize("name", ENV_NAMES)
def test_no_nan_over_a_thousand_random_steps_and_deterministic(name):
    _, (proprio, qpos, ag, *_) = rollout(name, 1)
    assert np.isfinite(np.asarray(proprio)).all()
    assert np.isfinite(np.asarray(qpos)).all()
    assert np.isfinite(np.asarray(ag)).all()
    env, resets, random_rollout = compiled(name)
    _, (proprio2, *_) = random_rollout(resets, jax.random.PRNGKey(1))
    np.testing.assert_array_equal(np.asarray(proprio), np.asarray(proprio2))
    _, (proprio3, *_) = rollout(name, 2)
    assert not np.array_equal(np.asarray(proprio), np.asarray(proprio3))


@pytest.mark.parametrize("name", ENV_NAMES)
def test_culled_camera_frames_are_those_of_casting_every_ray(name):
    """The camera's culling (each moving geom cast against its window of rays, envs_mjx/camera.py) gives the geom
    maps and frames of casting every geom against every ray over the random rollout's scenes, bit for bit, though
    the two are compiled apart (one scene at a time against a batch): two geoms hit at the same distance up to
    rounding (overlapping links at a joint) tie, and the one merged first keeps the ray in both. The culling is in
    force: nearly every scene fits its windows (the rest, cast in full, are compared too), and the frames the
    rollout rendered are culled ones. Generic: the windows come from the model, whatever its camera pose."""
    env, _, _ = compiled(name)
    cam = env.camera
    _, (*_, images, xpos, xmat) = rollout(name, 1)
    images, xpos, xmat = (x[::10].reshape(-1, *x.shape[2:]) for x in (images, xpos, xmat))  # 100 scenes
    assert any(side is not None for side in cam.windows), cam.windows

    @jax.jit
    def maps(xpos, xmat):
        scenes = jax.vmap(lambda p, m: env.blank_data().replace(geom_xpos=p, geom_xmat=m))(xpos, xmat)
        full = jax.vmap(lambda d: (cam.geom_map(env.mjx_model, d, cull=False), cam.render(env.mjx_model, d)))
        # one scene at a time: each keeps its windows unless it itself does not fit them
        culled = jax.lax.map(lambda d: (cam.geom_map(env.mjx_model, d), cam.fits_windows(env.mjx_model, d)), scenes)
        return *full(scenes), *culled

    full_ids, full_images, ids, fits = (np.asarray(x) for x in maps(xpos, xmat))
    assert fits.mean() >= 0.9, fits.mean()
    assert len(np.unique(full_ids)) >= 3  # the scene is seen, not a blank frame
    np.testing.assert_array_equal(ids, full_ids)
    # the rollout's frames: culled, vmapped over its envs inside the rollout's program
    np.testing.assert_array_equal(np.asarray(images), full_images)


@pytest.mark.parametrize("name", ENV_NAMES)
def test_reward_is_sparse_and_batched(name):
    env, _, _ = compiled(name)
    g = env.observation_spec.goal_size
    goal = np.zeros((3, g), np.float32)
    ag = goal.copy()
    ag[1, 0] = 0.5 * env.epsilon
    ag[2, 0] = 2.0 * env.epsilon
    np.testing.assert_array_equal(np.asarray(env.compute_reward(ag, goal)), [0.0, 0.0, -1.0])


@pytest.mark.parametrize("name", ENV_NAMES)
def test_nan_action_is_rejected_outside_jit(name):
    env, resets, _ = compiled(name)
    state = jax.tree.map(lambda x: x[0], resets)
    with pytest.raises(ValueError, match="NaN"):
        env.step(state, jnp.full(env.action_size, jnp.nan))


@pytest.mark.parametrize("name", ENV_NAMES)
def test_mjx_matches_mujoco_mj_step(name):
    """Same model, same controls: MJX (float32) and native MuJoCo (float64) agree on qpos within 1e-3 over 100
    substeps; a mismatched integrator or actuator model differs by 0.05 or more."""
    env, resets, _ = compiled(name)
    m = env.mj_model
    state = jax.tree.map(lambda x: x[3], resets)
    d = mujoco.MjData(m)
    d.qpos[:] = np.asarray(state.data.qpos)
    d.qvel[:] = np.asarray(state.data.qvel)
    d.ctrl[:] = np.asarray(state.data.ctrl)
    d.mocap_pos[:] = np.asarray(state.data.mocap_pos)
    d.mocap_quat[:] = np.asarray(state.data.mocap_quat)
    mujoco.mj_forward(m, d)
    rng = np.random.default_rng(0)
    low, high = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    ctrls = rng.uniform(low, high, size=(100 // env.n_substeps + 1, m.nu)).astype(np.float32)
    mjx_step = jax.jit(mujoco.mjx.step)
    data = state.data
    for i in range(100):
        if i % env.n_substeps == 0:
            ctrl = ctrls[i // env.n_substeps]
            # use the ctrl MJX will see (float32) on both sides
            d.ctrl[:] = ctrl
            data = data.replace(ctrl=jnp.asarray(ctrl))
        mujoco.mj_step(m, d)
        data = mjx_step(env.mjx_model, data)
        np.testing.assert_allclose(np.asarray(data.qpos), d.qpos, atol=1e-3, err_msg=f"step {i}")


def test_set_options_overrides_the_physics_and_rejects_what_it_cannot_use():
    env = envs_mjx.make("planar_reach", render=False)
    env.set_options(iterations="3", timestep=0.005, cone="elliptic")
    assert env.mj_model.opt.iterations == 3 and int(env.mjx_model.opt.iterations) == 3
    assert int(env.mjx_model.opt.cone) == int(mujoco.mjtCone.mjCONE_ELLIPTIC)
    assert env.n_substeps == 8 and float(env.mjx_model.opt.timestep) == pytest.approx(0.005)
    with pytest.raises(ValueError, match="not a scalar physics option"):
        env.set_options(frobnicate=1)
    with pytest.raises(ValueError, match="valid cones are pyramidal, elliptic"):
        env.set_options(cone="round")
    with pytest.raises(ValueError, match="does not divide"):
        env.set_options(timestep=0.03, iterations=7)
    assert env.mj_model.opt.iterations == 3 and env.n_substeps == 8  # nothing half-applied
