"""A new task is one module and one registry line (docs/usage.md, "Where new things go"): a toy task, its model a few
lines of MJCF and its presets and learning-curve budget on its class, registered here, trains through
`experiments.run` and through a one-cell `experiments.paper.curves --tasks toy` with nothing else edited. And every
registered task's declaration holds: its presets name config fields, its contract a section of the docs."""

import csv
import json
import os
import re

import jax
import mujoco
import pytest

import envs_mjx
from bidal_jax.config import AGENTS
from envs_mjx.base import JointReachEnv
from envs_mjx.task import Task
from experiments import cli, run
from experiments.paper import curves, protocol
from tests.helpers import REPO

# one hinge turned by a position servo, and the camera every env has
TOY_XML = """
<mujoco model="toy">
  <option timestep="0.02"/>
  <asset><material name="grey" rgba="0.5 0.5 0.5 1"/></asset>
  <worldbody>
    <camera name="top" pos="0 0 0.5"/>
    <body name="arm">
      <joint name="hinge" type="hinge" axis="0 0 1" range="-1.5 1.5"/>
      <geom type="capsule" fromto="0 0 0 0.1 0 0" size="0.01" mass="0.1" material="grey"/>
    </body>
  </worldbody>
  <actuator><position joint="hinge" kp="2"/></actuator>
</mujoco>
"""
TOY_SIZES = {"num_envs": 4, "cycles_per_epoch": 1, "updates_per_cycle": 2, "batch_size": 8, "buffer_episodes": 8,
             "eval_envs": 4}


class Toy(JointReachEnv):
    """Turn the hinge to a goal angle: proprio (q, qdot), A = G = 1, success within 0.1 rad after 5 steps."""

    name = "toy"
    task = Task(contract="docs/usage.md#where-new-things-go", presets={"run": {"epochs": 2}, "train": TOY_SIZES},
                image_presets={"run": {"epochs": 3}}, paper_epochs=1)

    def __init__(self, render: bool = True):
        super().__init__(mujoco.MjModel.from_xml_string(TOY_XML), max_delta=0.2, goal_size=1, camera_name="top",
                         episode_length=5, epsilon=0.1, render=render)

    def _reset_data(self, key):
        key_start, key_goal = jax.random.split(key)
        q0, goal = (jax.random.uniform(k, (1,), minval=self._q_low, maxval=self._q_high) for k in (key_start, key_goal))
        return self.blank_data().replace(qpos=q0, ctrl=q0), goal

    def _achieved_goal(self, data):
        return data.qpos


@pytest.fixture
def toy(monkeypatch):
    """The toy task, registered for one test."""
    monkeypatch.setattr(envs_mjx, "_REGISTRY", dict(envs_mjx._REGISTRY))
    envs_mjx.register("toy", f"{__name__}:Toy")


def epochs_of(run_dir) -> list[int]:
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        return [int(row["epoch"]) for row in csv.DictReader(f)]


def test_a_registered_toy_task_trains_through_the_run_command_and_the_learning_curves(toy, tmp_path, capsys):
    # its presets: the task's for every agent, its image presets over them for an agent that learns from images
    assert cli.resolve({"env": "toy", "agent": "proprio_baseline"}).run.epochs == 2
    assert cli.resolve({"env": "toy", "agent": "visual_bidal"}).run.epochs == 3
    assert "toy" in cli.run_description() and protocol.paper_epochs()["toy"] == 1
    run_dir = tmp_path / "run"
    assert run.main(["--env", "toy", "--agent", "proprio_baseline", "--run-dir", str(run_dir), "--quiet"]) == 0
    assert epochs_of(run_dir) == [1, 2]
    with open(run_dir / "config.json") as f:
        train = json.load(f)["train"]
    assert {k: train[k] for k in TOY_SIZES} == TOY_SIZES
    out = tmp_path / "curves"
    argv = ["--tasks", "toy", "--agents", "proprio_baseline", "--seeds", "1", "--out", str(out), "--quiet"]
    assert curves.main(argv) == 0
    printed = capsys.readouterr().out
    # its budget is the task's own; results/ has not timed it, so its estimate is the longest measured epoch's
    assert "toy proprio_baseline, 1 seed(s), exploration starts 0; 1 epochs × 20 = 20 env steps per seed" in printed
    assert "not measured in results/scaling/epochs, estimated as the longest measured epoch: toy as " in printed
    assert epochs_of(out / "toy" / "proprio_baseline") == [1]
    assert "| proprio_baseline |" in (out / "table.md").read_text()


def test_every_task_resolves_for_every_agent_and_names_a_section_of_the_docs():
    for name in envs_mjx.names():
        for agent in AGENTS:
            cli.resolve({"env": name, "agent": agent})  # ConfigError for a preset field the configs lack
        path, _, anchor = envs_mjx.task(name).contract.partition("#")
        with open(os.path.join(REPO, path), encoding="utf-8") as f:
            headings = [line.lstrip("#").strip() for line in f if line.startswith("#")]
        assert anchor in [re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings], name


def test_a_variant_s_lineage_names_the_task_it_derives_from_and_a_task_only_itself():
    assert envs_mjx.lineage("nicol_slide_ee_obj") == ("nicol_slide_ee_obj", "nicol_slide")
    assert envs_mjx.lineage("nicol_lift_reduced") == ("nicol_lift_reduced", "nicol_lift")
    assert [envs_mjx.lineage(name) for name in ("planar_reach", "nicol_lift")] == [("planar_reach",), ("nicol_lift",)]
    assert envs_mjx.lineage("removed_task") == ("removed_task",)  # a run's task the registry no longer has
