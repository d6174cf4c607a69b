"""Transfer (paper Sec. IV-C; bidal_jax/run/transfer.py): a run started with --init-from holds the source's
encoder, forward and inverse models (its proprio rows matched by segment name), with fresh optimisers and,
unless --init-normaliser inherit, a fresh proprio normaliser, read without the replay buffer; mismatches are
refused before anything is written.

The mechanism is tested on planar_reach (proprio q 2, qdot 2) as the source and a planar_reach
without qdot as the target: one source run and one transferred run (an image agent compiles in
about a minute on a CPU)."""

import csv
import dataclasses
import json
import os
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs_mjx
from bidal_jax import normalizer
from bidal_jax.agents import ddpg
from bidal_jax.config import Config
from bidal_jax.run import checkpoint, preflight, transfer
from bidal_jax.train import make_train
from envs_mjx.planar_reach import PlanarReach
from experiments import cli, run
from experiments.paper import grid
from tests.helpers import assert_refused, restored_state

NO_QDOT, RENAMED = "planar_reach_noqdot", "planar_reach_renamed"
SOURCE_SEEDS, SEEDS = 3, 2
PARTS = ("encoder", "forward", "inverse")
TINY = [
    "--agent", "multimodal_bidal", "--num-envs", "4", "--cycles-per-epoch", "1", "--updates-per-cycle", "2",
    "--batch-size", "8", "--buffer-episodes", "8", "--eval-envs", "4", "--conv-channels", "4", "--vision-features", "8",
    "--proprio-features", "8", "--latent-size", "8", "--embed-size", "8", "--hidden-size", "16", "--hidden-layers", "1",
    "--model-hidden-size", "16", "--epochs", "1", "--quiet",
]


class PlanarReachNoQdot(PlanarReach):
    """planar_reach without qdot: proprio q only (2 features)."""

    name = NO_QDOT

    def __init__(self, render: bool = True):
        super().__init__(render=render)
        self.observation_spec = self.observation_spec.without(("qdot",))


class PlanarReachRenamed(PlanarReach):
    """planar_reach with qdot named qvel: the source's sizes, but a segment it lacks."""

    name = RENAMED

    def __init__(self, render: bool = True):
        super().__init__(render=render)
        self.observation_spec = dataclasses.replace(self.observation_spec, proprio_segments=(("q", 2), ("qvel", 2)))

    def _proprio(self, data):
        return {"q": data.qpos, "qvel": data.qvel}


@pytest.fixture(scope="module", autouse=True)
def registered():
    """The two test envs, registered for this module only."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(envs_mjx, "_REGISTRY", dict(envs_mjx._REGISTRY))
        envs_mjx.register(NO_QDOT, f"{__name__}:PlanarReachNoQdot")
        envs_mjx.register(RENAMED, f"{__name__}:PlanarReachRenamed")
        yield


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A trained planar_reach run of SOURCE_SEEDS seeds, and a copy of it without replay buffers."""
    root = tmp_path_factory.mktemp("transfer")
    run_dir, copy = str(root / "source"), str(root / "source_without_buffer")
    assert run.main([*TINY, "--env", "planar_reach", "--seeds", str(SOURCE_SEEDS), "--run-dir", run_dir]) == 0
    shutil.copytree(run_dir, copy)
    for step in checkpoint.steps(os.path.join(copy, "checkpoints")):
        shutil.rmtree(os.path.join(copy, "checkpoints", str(step), "buffer"))
    return run_dir, copy


def _copy(tree):
    return jax.tree.map(np.array, tree)


def _leaves(tree) -> dict:
    return {checkpoint.leaf_name(p): np.asarray(x) for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]}


@pytest.fixture(scope="module")
def transferred(source, tmp_path_factory):
    """A run of planar_reach without qdot started from the buffer-less source copy, with its state
    before and after the transfer as run.main built it."""
    captured = {}
    real = transfer.make_initializer

    def recording(*args, **kwargs):
        initialize = real(*args, **kwargs)

        def recorded(state):
            captured["fresh"] = _copy(state)  # copies: the epoch donates the state
            new = initialize(state)
            captured["initial"] = _copy(new)
            return new

        return recorded

    run_dir = str(tmp_path_factory.mktemp("transferred") / "run")
    argv = [*TINY, "--env", NO_QDOT, "--seeds", str(SEEDS), "--init-from", source[1], "--run-dir", run_dir]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(transfer, "make_initializer", recording)
        assert run.main(argv) == 0
    return run_dir, captured["fresh"], captured["initial"]


@pytest.fixture(scope="module")
def source_state(source):
    """The source's whole latest training state, restored the ordinary way (buffer included)."""
    return jax.device_get(restored_state(source[0])[0])


def test_restored_parts_equal_the_sources_by_name_and_the_proprio_rows_are_those_of_q(transferred, source_state):
    _, fresh, initial = transferred
    for part in PARTS:
        want = _leaves(source_state.params[part])
        for tree in ("params", "target_params"):
            got = _leaves(getattr(initial, tree)[part])
            assert set(got) == set(want), (part, tree)
            for name, value in got.items():
                expected = want[name][:SEEDS]  # seed i from the source's seed i
                if f"{part}/{name}" == ddpg.BIDAL.proprio_kernel:
                    assert want[name].shape == (SOURCE_SEEDS, 4, 8)  # rows q0 q1 qdot0 qdot1
                    expected = expected[:, :2]
                np.testing.assert_array_equal(value, expected, err_msg=f"{tree}/{part}/{name}")
    # everything else is the fresh start: actor, critic and every optimiser state
    for part in ("actor", "critic"):
        for tree in ("params", "target_params"):
            for name, value in _leaves(getattr(initial, tree)[part]).items():
                np.testing.assert_array_equal(value, _leaves(getattr(fresh, tree)[part])[name])
    for name, value in _leaves(initial.opt_state).items():
        np.testing.assert_array_equal(value, _leaves(fresh.opt_state)[name], err_msg=name)
    assert not np.array_equal(_leaves(initial.params["encoder"])["params/proprio/bias"],
                              _leaves(fresh.params["encoder"])["params/proprio/bias"])


def test_the_proprio_normaliser_starts_afresh_by_default(transferred, source_state):
    _, fresh, initial = transferred
    assert float(source_state.proprio_norm.count[0]) > 0  # the source's statistics are real
    for a, b in zip(jax.tree.leaves((initial.proprio_norm, initial.goal_norm)),
                    jax.tree.leaves((fresh.proprio_norm, fresh.goal_norm))):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(initial.proprio_norm.count, np.zeros(SEEDS))


def test_inherit_normaliser_keeps_the_sources_statistics_with_the_kept_rows(transferred, source, source_state):
    _, fresh, _ = transferred
    run = dataclasses.replace(cli.resolve({"env": NO_QDOT, "seeds": SEEDS}).run, init_from=source[1],
                              init_normaliser="inherit")
    segments = envs_mjx.make(NO_QDOT, render=False).observation_spec.proprio_segments
    initial = transfer.make_initializer(run, segments, envs_mjx.make, log=lambda message: None)(fresh)
    src = source_state.proprio_norm
    np.testing.assert_array_equal(initial.proprio_norm.count, src.count[:SEEDS])
    for field in normalizer.FEATURE_FIELDS:
        expected = getattr(src, field)[:SEEDS, :2]
        np.testing.assert_array_equal(getattr(initial.proprio_norm, field), expected, err_msg=field)
    # goals reach only the fresh actor and critic: the goal normaliser starts fresh
    for a, b in zip(jax.tree.leaves(initial.goal_norm), jax.tree.leaves(fresh.goal_norm)):
        np.testing.assert_array_equal(a, b)


def test_a_transfer_run_recorded_before_init_normaliser_inherited(source):
    old = {"run": {"env": NO_QDOT, "init_from": source[1]}, "train": {}, "network": {}}
    assert Config.from_dict(old, "old").run.init_normaliser == "inherit"
    assert Config.from_dict({**old, "run": {"env": NO_QDOT}}, "scratch").run.init_normaliser == "fresh"
    today = cli.resolve({"env": NO_QDOT, "init_from": source[1]})
    assert grid.config_changes(old, today) == ("config differs: init_normaliser inherit → fresh, "
                                               "target_encoder target → online")


def test_the_transferred_run_trains_without_the_sources_buffer_and_records_its_source(transferred, source):
    run_dir, _, _ = transferred
    assert not os.path.exists(os.path.join(source[1], "checkpoints", "1", "buffer"))
    with open(os.path.join(run_dir, "metrics.csv"), newline="") as f:
        assert [int(r["epoch"]) for r in csv.DictReader(f)] == [1]
    with open(os.path.join(run_dir, "config.json")) as f:
        saved = json.load(f)["run"]
    assert (saved["init_from"], saved["init_parts"], saved["init_normaliser"]) == (source[1], ",".join(PARTS), "fresh")


def test_resume_keeps_the_transfer_fields_and_does_not_transfer_again(transferred, source, monkeypatch, capsys):
    run_dir, _, _ = transferred
    monkeypatch.setattr(transfer, "check", lambda *a, **k: pytest.fail("a resumed run was checked for transfer"))
    with preflight.prepare(
        {"run_dir": run_dir, "epochs": 2}, env_names=envs_mjx.names(), make_env=envs_mjx.make,
        preset=cli.task_preset, resume=True,
    ) as prepared:
        resumed = prepared.config.run
    assert (resumed.init_from, resumed.init_parts) == (source[1], ",".join(PARTS))
    assert_refused(
        ["--resume", "--run-dir", run_dir, "--init-from", source[0], "--quiet"],
        run_dir,
        ["--init-from", "differs from the checkpoint's"],
        capsys,
    )


def test_row_map_picks_source_rows_by_segment_name_in_the_targets_order():
    source = (("a", 2), ("b", 3), ("c", 1))
    assert transfer.row_map(source, (("c", 1), ("a", 2))).tolist() == [5, 0, 1]
    assert transfer.row_map(source, (("b", 3),)).tolist() == [2, 3, 4]
    with pytest.raises(ValueError, match="unknown proprio segment 'd'; segments are a, b, c"):
        transfer.row_map(source, (("a", 2), ("d", 1)))
    with pytest.raises(ValueError, match="segment b has 3 features in the source, 2 in this run"):
        transfer.row_map(source, (("b", 2),))


def test_apply_puts_the_planned_rows_in_the_planned_order(transferred, source_state):
    _, fresh, _ = transferred
    mapped = transfer.row_mapped(f"params/{ddpg.BIDAL.proprio_kernel}")
    plan = transfer.Plan("", 1, ("encoder",), {}, np.array([3, 0]), SEEDS, mapped)  # qdot1, then q0
    restored = {
        "params": {"encoder": source_state.params["encoder"]},
        "proprio_norm": dataclasses.asdict(source_state.proprio_norm),
    }
    new = transfer.apply(plan, fresh, restored)
    kernel = _leaves(source_state.params["encoder"])["params/proprio/kernel"]
    np.testing.assert_array_equal(_leaves(new.params["encoder"])["params/proprio/kernel"], kernel[:SEEDS][:, [3, 0]])
    np.testing.assert_array_equal(new.proprio_norm.mean, source_state.proprio_norm.mean[:SEEDS][:, [3, 0]])
    np.testing.assert_array_equal(new.goal_norm.mean, fresh.goal_norm.mean)  # only what the plan restores


def test_reduced_lift_keeps_the_slide_rows_of_its_segments():
    from envs_mjx.nicol import PROPRIO_SEGMENTS, REDUCED_DROP

    reduced = tuple(s for s in PROPRIO_SEGMENTS if s[0] not in REDUCED_DROP)
    # ee_pos, ee_rot, obj_pos (rows 0-8), then ee_velp, q, qdot (rows 21-39) of nicol_slide's 40
    assert transfer.row_map(PROPRIO_SEGMENTS, reduced).tolist() == [*range(9), *range(21, 40)]


def test_init_from_names_a_run_and_optionally_a_checkpoint():
    assert transfer.parse_init_from("runs/a") == ("runs/a", None)
    assert transfer.parse_init_from("runs/a:12") == ("runs/a", "12")
    assert transfer.parse_init_from("runs/a:best") == ("runs/a", "best")
    assert transfer.parse_init_from("c:/x") == ("c:/x", None)
    assert transfer.parse_parts("encoder, forward,inverse") == PARTS


@pytest.fixture(scope="module")
def proprio_source(tmp_path_factory):
    """A checkpoint of a proprio_baseline run on planar_reach (its initial state: nothing trained)."""
    run_dir = str(tmp_path_factory.mktemp("proprio") / "run")
    config = cli.resolve(
        {"env": "planar_reach", "agent": "proprio_baseline", "seeds": SEEDS, "buffer_episodes": 8, "num_envs": 4}
    )
    init, _ = make_train(envs_mjx.make("planar_reach", render=False), config)
    shapes = jax.eval_shape(jax.vmap(init), jax.ShapeDtypeStruct((SEEDS, 2), jnp.uint32))
    mngr = checkpoint.manager(os.path.join(run_dir, "checkpoints"))
    checkpoint.save(mngr, 1, jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), shapes), config.to_dict(), 0.0)
    mngr.close()
    return run_dir


REFUSALS = {
    "missing source": (
        lambda src, pro, tmp: ["--init-from", str(tmp / "none")],
        ["--init-from", "none", "does not exist"],
    ),
    "missing checkpoint": (lambda src, pro, tmp: ["--init-from", f"{src}:7"], ["no checkpoint 7 in", "it has [1]"]),
    "part the source lacks": (
        lambda src, pro, tmp: ["--init-from", pro],
        ["--init-parts encoder,forward,inverse", "the source (proprio_baseline) has no encoder", "actor, critic"],
    ),
    "part this agent lacks": (
        lambda src, pro, tmp: ["--init-from", src, "--agent", "multimodal_baseline"],
        ["this run's agent multimodal_baseline has no forward"],
    ),
    "unknown part": (lambda src, pro, tmp: ["--init-from", src, "--init-parts", "encoder,decoder"], ["has no decoder"]),
    "part list syntax": (
        lambda src, pro, tmp: ["--init-from", src, "--init-parts", "encoder,,inverse"],
        ["--init-parts encoder,,inverse", "comma-separated"],
    ),
    "leaf of another shape": (
        lambda src, pro, tmp: ["--init-from", src, "--latent-size", "6"],
        ["params/encoder/params/Dense_0/bias is (8,) float32 per seed in the source", "this run needs (6,) float32"],
    ),
    "encoder of another agent": (
        lambda src, pro, tmp: ["--init-from", src, "--agent", "visual_bidal"],
        ["the source has params/encoder/params/proprio/bias ((8,) per seed), this run has none"],
    ),
    "segments the source lacks": (
        lambda src, pro, tmp: ["--init-from", src, "--env", RENAMED],
        [f"this run's env {RENAMED} does not fit planar_reach's", "unknown proprio segment 'qvel'"],
    ),
    "more seeds than the source": (
        lambda src, pro, tmp: ["--init-from", src, "--seeds", "4"],
        ["--seeds 4", "has 3 seed(s)", "at least 4"],
    ),
}


@pytest.mark.parametrize("case", list(REFUSALS))
def test_bad_transfer_is_refused_before_anything_is_written(case, source, proprio_source, tmp_path, capsys):
    extra, expected = REFUSALS[case]
    run_dir = tmp_path / "run"
    argv = [
        *TINY,
        "--env",
        NO_QDOT,
        "--seeds",
        str(SEEDS),
        "--run-dir",
        str(run_dir),
        *extra(source[0], proprio_source, tmp_path),
    ]
    assert_refused(argv, run_dir, expected, capsys)
    assert not run_dir.exists()


def test_a_run_cannot_start_from_its_own_directory_it_would_delete(source, tmp_path, capsys):
    run_dir = tmp_path / "run"
    shutil.copytree(source[0], run_dir)
    argv = [*TINY, "--env", "planar_reach", "--run-dir", str(run_dir), "--overwrite", "--init-from", str(run_dir)]
    assert_refused(argv, run_dir, ["is this run's own --run-dir"], capsys)
