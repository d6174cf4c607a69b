"""Configs (bidal_jax/config.py): every field has its documentation and its rule beside it, and the
three configs travel as one value whose JSON form reads back, older records included."""

import dataclasses

import pytest

from bidal_jax.config import CONFIG_CLASSES, CONV_IMPLS, REMOVED_CONV_IMPLS, Config, Rule, recorded
from experiments.cli import resolve


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
