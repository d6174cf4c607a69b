"""Configs (bidal_jax/config.py): every field has its documentation and its rule beside it, and the
three configs travel as one value whose JSON form reads back."""

import dataclasses

from bidal_jax.config import CONFIG_CLASSES, Config, Rule, resolve


def test_every_config_field_has_its_help_and_rule():
    for group in CONFIG_CLASSES.values():
        for f in dataclasses.fields(group):
            assert f.metadata["help"], f.name
            assert isinstance(f.metadata["rule"], Rule), f.name


def test_the_config_value_round_trips_through_its_json_form_and_fills_newer_fields():
    config = resolve({"env": "nicol_slide", "agent": "visual_bidal", "num_envs": 8})
    assert config.train.num_envs == 8 and config.run.epochs == 100 and config.agent.uses_image
    assert Config.from_dict(config.to_dict(), "test") == config
    old = config.to_dict()
    del old["train"]["grad_clip"]  # a config.json written before the field existed
    assert Config.from_dict(old, "old").train.grad_clip == config.train.grad_clip
