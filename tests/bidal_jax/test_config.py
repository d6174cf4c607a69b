"""Configs (bidal_jax/config.py): every field has its documentation and its rule beside it, and the
three configs travel as one value whose JSON form reads back, older records included."""

import dataclasses
import os

import pytest

from bidal_jax import config as config_lib
from bidal_jax.config import (
    CONFIG_CLASSES,
    CONV_IMPLS,
    REMOVED_CONV_IMPLS,
    Config,
    ConfigError,
    Rule,
    RunConfig,
    TrainConfig,
    recorded,
)
from experiments.cli import resolve
from tests.helpers import REPO


def test_every_config_field_has_its_help_and_rule():
    for group in CONFIG_CLASSES.values():
        for f in dataclasses.fields(group):
            assert f.metadata["help"], f.name
            assert isinstance(f.metadata["rule"], Rule), f.name


def test_the_config_value_round_trips_through_its_json_form_and_fills_newer_fields():
    config = resolve({"env": "nicol_slide", "agent": "visual_bidal", "num_envs": 8})
    assert config.train.num_envs == 8 and config.run.epochs == 30 and config.agent.uses_image
    assert Config.from_dict(config.to_dict(), "test") == config
    old = config.to_dict()
    del old["train"]["grad_clip"]  # a config.json written before the field existed
    assert Config.from_dict(old, "old").train.grad_clip == config.train.grad_clip


@pytest.mark.parametrize("removed", REMOVED_CONV_IMPLS)
def test_a_stored_config_of_a_removed_conv_impl_reads_as_patch(removed):
    """A config.json or checkpoint of a run that computed its convs another way (taps, native, stacked: the same
    function of the same parameters) still loads, as patch; an unknown implementation is left for the checks."""
    stored = resolve({"env": "ur5_reach"}).to_dict()
    stored["network"]["conv_impl"] = removed
    assert Config.from_dict(stored, "old").network.conv_impl == "patch"
    assert recorded("network", {**stored["network"], "conv_impl": "fft"})["conv_impl"] == "fft"
    assert removed not in CONV_IMPLS


def test_a_stored_config_older_than_target_encoder_reads_the_target_encoder():
    """Runs recorded before `target_encoder` trained their critics on the target encoder's φ(s_{t+1}): they resume and
    evaluate so; a new run takes the online encoder's."""
    stored = resolve({"env": "ur5_reach"}).to_dict()
    assert stored["train"]["target_encoder"] == "online"
    del stored["train"]["target_encoder"]
    assert Config.from_dict(stored, "old").train.target_encoder == "target"


def test_a_preset_lies_between_the_defaults_and_the_options_given_and_names_config_fields_only():
    preset = {"run": {"epochs": 7}, "train": {"num_envs": 4, "batch_size": 32}}
    config = config_lib.resolve({"env": "planar_reach", "num_envs": 8}, lambda env, agent: preset)
    assert (config.run.epochs, config.train.num_envs, config.train.batch_size) == (7, 8, 32)
    assert config.train.gamma == TrainConfig().gamma and config.run.env == "planar_reach"
    with pytest.raises(ConfigError, match="the task's preset sets train.num_env, model.size, not a config field"):
        config_lib.resolve({}, lambda env, agent: {"train": {"num_env": 4}, "model": {"size": 1}})


def test_the_usage_guide_states_the_checkpoint_intervals_the_code_sets():
    with open(os.path.join(REPO, "docs", "usage.md"), encoding="utf-8") as f:
        usage = f.read()
    nicol = {resolve({"env": env}).run.checkpoint_every for env in ("nicol_slide", "nicol_lift", "nicol_lift_reduced")}
    assert nicol == {10} and RunConfig().checkpoint_every == 5
    assert f"every `--checkpoint-every` epochs ({RunConfig().checkpoint_every}; 10 on the NICOL tasks" in usage
    assert "NICOL presets save a checkpoint every 10 epochs" in usage
