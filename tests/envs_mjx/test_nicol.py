"""nicol_slide / nicol_lift tests (docs/tasks.md "nicol_slide and nicol_lift"): proprio layout,
reduced variant, reset distributions, Cartesian hand tracking, joint limits and the
scripted controllers that prove both tasks solvable in this physics.

The shared API tests (shapes, NaN, determinism, MJX vs mj_step) live in test_env_contract.py.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

import envs_mjx
from bidal_jax import acting
from envs_mjx import nicol
from envs_mjx.nicol import NicolLift, NicolSlide
from experiments.probes.grasping import run_episodes

TASKS_SEGMENTS = (
    ("ee_pos", 3), ("ee_rot", 3), ("obj_pos", 3), ("obj_rot", 3), ("obj_rel_pos", 3),
    ("obj_velp", 3), ("obj_velr", 3), ("ee_velp", 3), ("q", 8), ("qdot", 8),
)
REDUCED_NAMES = ("ee_pos", "ee_rot", "obj_pos", "ee_velp", "q", "qdot")
N_RESETS = 512
N_EPISODES = 100


@pytest.fixture(scope="module")
def lift():
    return NicolLift(render=False)


@pytest.fixture(scope="module")
def slide():
    return NicolSlide(render=False)


@pytest.fixture(scope="module")
def lift_resets(lift):
    return jax.jit(jax.vmap(lift.reset))(jax.random.split(jax.random.PRNGKey(0), N_RESETS))


@pytest.fixture(scope="module")
def slide_resets(slide):
    return jax.jit(jax.vmap(slide.reset))(jax.random.split(jax.random.PRNGKey(1), N_RESETS))


def test_proprio_has_the_forty_named_features_of_tasks_md(lift, slide):
    for env in (lift, slide):
        assert env.observation_spec.proprio_segments == TASKS_SEGMENTS
        assert env.observation_spec.proprio_size == 40
        assert env.action_size == 7 and env.observation_spec.goal_size == 3
        assert env.episode_length == 50 and env.epsilon == 0.05


def test_reduced_lift_keeps_exactly_the_28_named_features(lift, lift_resets):
    reduced = envs_mjx.make("nicol_lift_reduced", render=False)
    assert reduced.observation_spec.segment_names == REDUCED_NAMES
    assert reduced.observation_spec.proprio_size == 28
    assert isinstance(reduced, envs_mjx.Env) and reduced.name == "nicol_lift_reduced"
    key = jax.random.PRNGKey(0)
    full = jax.tree.map(lambda x: x[0], lift_resets)
    small = jax.jit(reduced.reset)(jax.random.split(key, N_RESETS)[0])
    spec = lift.observation_spec
    expected = np.concatenate([np.asarray(full.obs["proprio"][spec.segment_slice(n)]) for n in REDUCED_NAMES])
    # a vmapped and an unbatched reset are two XLA programs: equal up to float rounding (the
    # settled velocities, ~1e-7, differ by ~3e-8); a wrong or shifted segment differs by far more
    np.testing.assert_allclose(np.asarray(small.obs["proprio"]), expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(small.obs["desired_goal"]), np.asarray(full.obs["desired_goal"]))


@pytest.mark.parametrize("name, kept", [("nicol_slide_ee", ("ee_pos",)), ("nicol_slide_ee_obj", ("ee_pos", "obj_pos"))])
def test_the_ladders_slide_variants_keep_exactly_their_segments(slide, slide_resets, name, kept):
    """The ladder's rungs (experiments.paper.ladder): nicol_slide's task, observing only the kept segments."""
    variant = envs_mjx.make(name, render=False)
    spec = variant.observation_spec
    assert isinstance(variant, NicolSlide) and variant.name == name
    assert spec.segment_names == kept and spec.proprio_size == 3 * len(kept) and spec.derived == ()
    assert spec.goal_segment == ("obj_pos" if "obj_pos" in kept else None)
    assert spec.shapes()["proprio"] == ((3 * len(kept),), jnp.float32)
    assert variant.physics_id == slide.physics_id
    full = jax.tree.map(lambda x: x[0], slide_resets)
    small = variant._observe(full.data, full.obs["desired_goal"])  # eager: no program compiled for the variant
    expected = np.concatenate([np.asarray(full.obs["proprio"][slide.observation_spec.segment_slice(n)]) for n in kept])
    np.testing.assert_allclose(np.asarray(small["proprio"]), expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(small["desired_goal"]), np.asarray(full.obs["desired_goal"]))


def test_keeping_an_unknown_segment_is_refused():
    class Colour(nicol.NicolSlideKept):
        name, keep = "nicol_slide_colour", ("ee_pos", "obj_colour")

    with pytest.raises(ValueError, match="nicol_slide_colour: cannot keep \\['obj_colour'\\]"):
        Colour(render=False)


def test_dropping_unknown_segment_names_is_refused(lift):
    with pytest.raises(ValueError, match="obj_colour"):
        lift.observation_spec.without(("obj_colour",))


def test_cube_starts_and_lift_goals_follow_the_contract(lift, lift_resets):
    spec = lift.observation_spec
    cube = np.asarray(lift_resets.obs["proprio"][:, spec.segment_slice("obj_pos")])
    centre = np.asarray(lift._cube_centre)
    assert np.abs(cube[:, :2] - centre[:2]).max() <= nicol.CUBE_START_RANGE + 1e-3
    np.testing.assert_allclose(cube[:, 2], nicol.TABLE_HEIGHT + nicol.CUBE_HALF, atol=2e-3)
    goal = np.asarray(lift_resets.obs["desired_goal"])
    assert np.abs(goal[:, :2] - cube[:, :2]).max() <= nicol.LIFT_GOAL_RANGE + 1e-3
    # HER's pick-and-place goals: half on the table (where the resting cube's centre is), half 5-25 cm above it
    height = goal[:, 2] - nicol.TABLE_HEIGHT
    on_table = np.isclose(height, nicol.CUBE_HALF, atol=1e-6)
    subsets = lift.goal_subsets(jnp.asarray(goal))
    air = np.asarray(subsets["air"])
    np.testing.assert_array_equal(air, ~on_table)
    np.testing.assert_array_equal(np.asarray(subsets["table"]), on_table)
    assert abs(air.mean() - 0.5) < 4 * np.sqrt(0.25 / len(air))
    assert height[air].min() >= nicol.LIFT_HEIGHT[0] - 1e-6 and height[air].max() <= nicol.LIFT_HEIGHT[1] + 1e-6
    assert abs(np.median(height[air]) - np.mean(nicol.LIFT_HEIGHT)) < 0.02  # uniform over the range
    # the goal marker sits at the goal
    np.testing.assert_allclose(np.asarray(lift_resets.data.mocap_pos[:, lift._goal_mocap]), goal, atol=1e-6)


def test_the_never_lift_floor_is_the_success_of_the_resting_cube_under_each_goal(lift, lift_resets):
    """A policy that slides the cube perfectly but never lifts it: success when the cube resting right under
    the goal is within ε, i.e. every table goal and the air goals less than ε above the resting cube."""
    goal = np.asarray(lift_resets.obs["desired_goal"])
    resting = goal.copy()
    resting[:, 2] = nicol.TABLE_HEIGHT + nicol.CUBE_HALF
    slid = np.asarray(lift.compute_reward(jnp.asarray(resting), jnp.asarray(goal))) == 0.0
    air = np.asarray(lift.goal_subsets(jnp.asarray(goal))["air"])
    floor = lift.never_lift_success()
    assert floor == pytest.approx({"all": 0.5625, "air": 0.125, "table": 1.0})
    assert abs(slid[air].mean() - floor["air"]) < 4 * np.sqrt(floor["air"] * (1 - floor["air"]) / air.sum())
    assert slid[~air].all()
    assert NicolLift(render=False, air_goal_probability=1.0).never_lift_success()["all"] == 0.125
    with pytest.raises(ValueError, match="air_goal_probability=1.5: must be in"):
        NicolLift(render=False, air_goal_probability=1.5)


def test_slide_goals_lie_on_the_table_around_the_start_region(slide, slide_resets):
    states = slide_resets
    goal = np.asarray(states.obs["desired_goal"])
    centre = np.asarray(slide._cube_centre)
    reach = nicol.CUBE_START_RANGE + nicol.SLIDE_GOAL_RANGE
    assert np.abs(goal[:, :2] - centre[:2]).max() <= reach + 1e-6
    assert np.abs(goal[:, :2] - centre[:2]).max() > 0.8 * reach  # the whole range is used
    np.testing.assert_allclose(goal[:, 2], centre[2], atol=1e-6)
    np.testing.assert_allclose(np.asarray(states.data.mocap_pos[:, slide._goal_mocap]), goal, atol=1e-6)


def test_hand_tracks_random_cartesian_commands_within_a_few_centimetres(lift):
    """After every control period the hand is within 4 cm of its commanded position, and the
    arm joints stay inside their limits. The target moves over the whole period (issue 24:
    the hand is led at ≤ 1.25 m/s instead of pulled by a jump), so the hand trails it by the
    weld's lag, ≈ 2·0.7/75 s × speed ≈ 2.3 cm at full speed (mean 17 mm, max 35 mm measured);
    before, the target jumped at the start of the period and the hand settled within 5 mm."""

    def record(step):
        state = step.next_state
        target = state.data.mocap_pos[:, lift._target_mocap]
        error = jnp.linalg.norm(state.data.xpos[:, lift._hand] - target, axis=-1)
        return error, state.data.qpos[:, lift._q_adr[:6]]

    run = jax.jit(lambda key: acting.rollout(lift, acting.random_policy(7), key, 16, record=record)[1])
    error, q = run(jax.random.PRNGKey(2))
    error, q = np.asarray(error), np.asarray(q)
    print(f"hand tracking error after one period: mean {1000 * error.mean():.1f} mm, max {1000 * error.max():.1f} mm")
    assert error.max() < 0.04
    low, high = lift.mj_model.jnt_range[lift._chain_joints[:6]].T
    assert (q >= low - 1e-3).all() and (q <= high + 1e-3).all()


def test_held_cube_start_keeps_the_cube_in_the_rising_hand(lift):
    """Native MuJoCo from the exploration start: with the grip closed, the cube follows the
    hand target 0.1 m up and stays within a few mm of the grasp point."""
    model = lift.mj_model
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("home").id)
    data.qpos[:], data.ctrl[:] = nicol.held_cube_start(model)
    mujoco.mj_forward(model, data)
    start = data.xpos[lift._cube].copy()
    for _ in range(25):  # one second: 4 mm per control period
        data.mocap_pos[lift._target_mocap, 2] += 0.004
        mujoco.mj_step(model, data, nstep=lift.n_substeps)
    assert data.xpos[lift._cube][2] - start[2] > 0.09
    assert np.linalg.norm(data.xpos[lift._cube] - data.xpos[lift._hand]) < 0.01


def test_exploration_reset_holds_the_cube_and_draws_the_reset_goal(lift, lift_resets):
    keys = jax.random.split(jax.random.PRNGKey(0), N_RESETS)[:8]
    eased = jax.jit(jax.vmap(lift.exploration_reset))(keys)
    spec = lift.observation_spec
    rel = np.asarray(eased.obs["proprio"][:, spec.segment_slice("obj_rel_pos")])
    closure = np.asarray(eased.obs["proprio"][:, spec.segment_slice("q")][:, 6])
    assert (np.linalg.norm(rel, axis=1) < 0.01).all() and (closure > 1.0).all()
    reset_goals = np.asarray(lift_resets.obs["desired_goal"][:8])
    np.testing.assert_array_equal(np.asarray(eased.obs["desired_goal"]), reset_goals)
    assert lift.has_exploration_start and not NicolSlide.has_exploration_start


# 0.97 slide, 1.00 lift measured with a 0.015 m carry step (0.82 slide with 0.01), see assets/README.md
@pytest.mark.parametrize("task,threshold", [("slide", 0.9), ("lift", 0.9)])
def test_scripted_grasp_controller_solves_the_task(task, threshold, slide, lift, slide_resets, lift_resets):
    env, resets = {"slide": (slide, slide_resets), "lift": (lift, lift_resets)}[task]
    # the two tasks share their step, so the second compile is a persistent-cache hit
    first = jax.tree.map(lambda x: x[:N_EPISODES], resets)
    success = jax.jit(run_episodes, static_argnums=0)(env, first)
    rate = float(np.asarray(success).mean())
    print(f"nicol_{task}: scripted success {rate:.2f} over {N_EPISODES} episodes")
    assert rate >= threshold
