"""The Gymnasium adapters (envs_mjx.gym): Gymnasium's env checker, the vector env's spaces,
truncation with same-step autoreset, rewards, seeding, the image option and rendering, and the edges:
wrongly shaped actions refused before the step, non-finite goals rewarded as failures.

All on planar_reach with 1 and 2 envs; the compiled functions are shared per (task, envs, image).
"""

import re

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import envs_mjx
import envs_mjx.gym as eg

NUM_ENVS = 2
T = 50  # planar_reach's episode length


@pytest.fixture(scope="module")
def envs():
    vector = eg.VectorGoalEnv("planar_reach", NUM_ENVS, render_mode="rgb_array")
    yield vector
    vector.close()


def random_actions(envs, seed: int, steps: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-1, 1, (steps, *envs.action_space.shape)).astype(np.float32)


# unbounded Boxes for velocities and goals are the goal-env convention (Gymnasium-Robotics too)
@pytest.mark.filterwarnings("ignore:.*Box observation space m.* value is -?infinity")
def test_env_checker_passes_on_the_single_env():
    env = gymnasium.make("bidal/PlanarReach-v0", render_mode="rgb_array")
    assert isinstance(env.unwrapped, eg.GoalEnv)
    check_env(env.unwrapped)  # raises AssertionError on any failed check
    env.close()


def test_every_task_is_registered_with_single_and_vector_entry_points():
    for name in envs_mjx.names():
        spec = gymnasium.spec(eg.gym_id(name))
        assert spec.kwargs == {"name": name} and spec.vector_entry_point.endswith(":VectorGoalEnv")
    vector = gymnasium.make_vec("bidal/PlanarReach-v0", num_envs=NUM_ENVS)
    assert isinstance(vector, eg.VectorGoalEnv) and vector.num_envs == NUM_ENVS
    assert vector.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.SAME_STEP


def test_observations_and_infos_have_the_declared_shapes_and_dtypes(envs):
    obs, info = envs.reset(seed=0)
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}  # no image unless asked for
    assert obs["observation"].shape == (NUM_ENVS, 4) and obs["desired_goal"].shape == (NUM_ENVS, 2)
    assert all(v.dtype == np.float32 for v in obs.values())
    assert obs in envs.observation_space
    assert info["is_success"].shape == (NUM_ENVS,) and info["is_success"].dtype == bool
    obs, reward, terminated, truncated, info = envs.step(random_actions(envs, 0, 1)[0])
    assert obs in envs.observation_space
    assert reward.shape == terminated.shape == truncated.shape == (NUM_ENVS,)
    assert not terminated.any() and not truncated.any()
    assert np.array_equal(info["is_success"], reward == 0.0)


def test_truncation_at_T_with_same_step_autoreset_and_compute_reward(envs):
    obs, _ = envs.reset(seed=1)
    goal = obs["desired_goal"]
    achieved, rewards = [], []
    for t, action in enumerate(random_actions(envs, 1, T + 1), start=1):
        obs, reward, terminated, truncated, info = envs.step(action)
        assert not terminated.any()
        assert truncated.all() == (t == T) and truncated.any() == (t == T)
        if t < T:
            achieved.append(obs["achieved_goal"])
            rewards.append(reward)
            assert np.array_equal(obs["desired_goal"], goal)
        elif t == T:
            final = np.stack([info["final_obs"][i]["achieved_goal"] for i in range(NUM_ENVS)])
            achieved.append(final)
            rewards.append(reward)
            assert info["_final_obs"].all() and info["final_info"]["is_success"].dtype == bool
            assert np.array_equal(info["final_info"]["is_success"], reward == 0.0)
            assert np.array_equal(info["final_obs"][0]["desired_goal"], goal[0])
            assert not np.array_equal(obs["desired_goal"], goal)  # the next episode's goals
        else:
            assert "final_obs" not in info  # the new episode runs on
    achieved, rewards = np.stack(achieved), np.stack(rewards)
    assert np.array_equal(envs.compute_reward(achieved, np.broadcast_to(goal, achieved.shape), {}), rewards)
    assert rewards.min() == -1.0 and rewards.max() <= 0.0


def test_seeded_reset_and_steps_are_deterministic(envs):
    actions = random_actions(envs, 2, 3)

    def rollout(seed):
        first, _ = envs.reset(seed=seed)
        return [first] + [envs.step(a)[0] for a in actions]

    same, other = rollout(7), rollout(7)
    for a, b in zip(same, other):
        assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(rollout(8)[0]["desired_goal"], same[0]["desired_goal"])


def test_image_is_observed_only_when_asked_for():
    obs, _ = eg.VectorGoalEnv("planar_reach", NUM_ENVS, image=True).reset(seed=0)
    assert obs["image"].shape == (NUM_ENVS, 42, 42, 1) and obs["image"].dtype == np.uint8
    assert obs["image"].max() > obs["image"].min()  # the arm and the target are drawn


def test_render_draws_the_first_env_with_mujoco(envs):
    envs.reset(seed=0)
    frames = envs.render()
    assert len(frames) == 1
    frame = frames[0]
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.shape[0] >= 240 and frame.shape[1] >= 320
    assert frame.std() > 1.0  # not a blank image


def test_bad_arguments_are_refused_with_clear_errors(envs):
    with pytest.raises(ValueError, match="unknown env 'nope'; valid envs: planar_reach"):
        eg.VectorGoalEnv("nope")
    with pytest.raises(ValueError, match="num_envs 0: must be an integer >= 1"):
        eg.VectorGoalEnv("planar_reach", 0)
    with pytest.raises(ValueError, match="render_mode 'human'"):
        eg.VectorGoalEnv("planar_reach", render_mode="human")
    envs.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions have shape \(3, 2\); expected \(2, 2\)"):
        envs.step(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        envs.step(np.full((NUM_ENVS, 2), np.nan))


def test_wrongly_shaped_actions_are_refused_before_the_step_and_the_state_is_kept(envs):
    single = eg.GoalEnv("planar_reach")
    obs, _ = single.reset(seed=0)
    for action in (np.zeros((2, 2)), np.zeros(3), np.zeros(())):  # (2, 2) once reached the jitted step
        with pytest.raises(ValueError, match=rf"action has shape {re.escape(str(np.shape(action)))}; expected \(2,\)"):
            single.step(action)
    after, *_ = single.step(np.zeros(2))  # the state the refused actions left: the reset's, one step on
    assert single.vector._carry is not None and after["desired_goal"].tolist() == obs["desired_goal"].tolist()
    envs.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions have shape \(2, 2, 1\); expected \(2, 2\)"):
        envs.step(np.zeros((NUM_ENVS, 2, 1)))
    single.close()


def test_compute_reward_counts_a_goal_that_is_not_finite_as_a_failure(envs):
    # NaN against anything, and inf against inf, have a NaN distance (it once gave -0.0: a success)
    achieved = np.array([[np.nan, 0.0], [np.inf, 0.0], [0.0, 0.0]], np.float32)
    desired = np.array([[0.0, 0.0], [np.inf, 0.0], [0.0, 0.0]], np.float32)
    reward = envs.compute_reward(achieved, desired, None)
    assert reward.tolist() == [-1.0, -1.0, 0.0] and not np.signbit(reward[2])
