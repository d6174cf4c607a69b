"""Each task's floor (envs_mjx/floors.py): the stored floors (results/floors, `python -m experiments.probes.floors`)
against the analytic values of the NICOL tasks and a small Monte Carlo of planar_reach, and the estimator on
hand-made samples."""

import jax
import numpy as np
import pytest

import envs_mjx
from envs_mjx import floors
from experiments import report

STORED = report.load_floors()
# nicol_slide: πε²/0.5²; nicol_lift: table πε²/0.2², air ∫ π(ε² − z²)/0.2² dz/0.2 over z in [0.025, ε], all their mean
EPS = 0.05
AIR = np.pi / 0.04 / 0.2 * (EPS**2 * (EPS - 0.025) - (EPS**3 - 0.025**3) / 3)
ANALYTIC = {("nicol_slide", "all"): np.pi * EPS**2 / 0.25, ("nicol_lift", "table"): np.pi * EPS**2 / 0.04,
            ("nicol_lift", "air"): AIR, ("nicol_lift", "all"): 0.5 * (np.pi * EPS**2 / 0.04 + AIR)}


def test_every_task_has_a_stored_floor_within_the_precision_asked():
    for task in ("planar_reach", "ur5_reach", "nicol_slide", "nicol_lift"):
        assert "all" in STORED[task] and STORED[task]["all"].half_width <= 0.005, task
    assert set(STORED["nicol_lift"]) == {"all", "air", "table"}
    assert STORED["nicol_lift"]["air"].share == pytest.approx(0.5, abs=0.01)


@pytest.mark.parametrize("task, subset", list(ANALYTIC))
def test_stored_nicol_floors_agree_with_their_analytic_values(task, subset):
    found = STORED[task][subset]
    assert abs(found.value - ANALYTIC[task, subset]) <= found.half_width, (found, ANALYTIC[task, subset])


def test_a_small_monte_carlo_of_planar_reach_agrees_with_the_stored_floor():
    found = floors.floor(envs_mjx.make("planar_reach", render=False), jax.random.key(7), rollouts=128,
                         resets=8_192, batch=128)["all"]
    stored = STORED["planar_reach"]["all"]
    assert abs(found.value - stored.value) <= np.hypot(found.half_width, stored.half_width)
    assert (found.resets, found.rollouts) == (8_192, 128)


def test_the_estimator_adds_the_rollouts_change_to_the_resets_success():
    start, start_in = np.array([1, 0, 0, 0]), np.array([True, True, True, False])
    first, last, rollout_in = np.array([1, 0, 0]), np.array([0, 0, 1]), np.ones(3, bool)
    value, half = floors.combine(start, start_in, first, last, rollout_in)
    assert value == pytest.approx(1 / 3 + 0.0)  # s_0 over the subset's 3 resets, plus the mean change (-1 + 1) / 3
    assert half == pytest.approx(1.959963984540054 * np.sqrt((1 / 3) / 3 + 1.0 / 3))
    # no change seen in M rollouts: its variance is taken as one change in M, not zero
    _, half = floors.combine(start, start_in, first, first, rollout_in)
    assert half == pytest.approx(1.959963984540054 * np.sqrt((1 / 3) / 3 + (1 / 3) / 3))
    with pytest.raises(ValueError, match="at least 2 resets"):
        floors.combine(start, np.zeros(4, bool), first, last, rollout_in)


def test_the_idle_action_holds_nicols_hand_open():
    action = np.asarray(floors.idle_action(envs_mjx.make("nicol_slide", render=False)))
    np.testing.assert_array_equal(action, [0, 0, 0, 0, 0, -1, -1])
    assert not np.asarray(floors.idle_action(envs_mjx.make("planar_reach", render=False))).any()
