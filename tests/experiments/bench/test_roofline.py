"""experiments.bench.roofline: the useful FLOPs and unavoidable bytes of each part of an update, and each part set
against its own floor; experiments.bench.updates --json, the measured side."""

import json

import jax
import pytest

from experiments.bench import floor_table, roofline
from experiments.bench import updates as bench_updates

TINY = "batch_size=8,buffer_episodes=32,num_envs=16,net.hidden_size=16,net.embed_size=8,net.conv_channels=2"


def conv_flops(channels: int, features: int) -> int:
    """The vision branch's useful FLOPs a frame, by hand: 3×3 convs 42 → 14 (stride 3, 1 channel in) → 7 → 4 → 4
    (strides 2, 2, 1), `channels` each, then the dense layer of the 4×4 map to `features`."""
    maps = [(14, 1), (7, channels), (4, channels), (4, channels)]  # (output side, input channels)
    return sum(2 * side * side * channels * 9 * c_in for side, c_in in maps) + 2 * 16 * channels * features


@pytest.fixture(scope="module")
def full_op_names():
    """Lowered with JAX's full source locations, whose op names carry the scopes (an earlier test of this process
    may have run `loop.short_source_locations`)."""
    before = jax.config.jax_include_full_tracebacks_in_locations
    jax.config.update("jax_include_full_tracebacks_in_locations", True)
    yield
    jax.config.update("jax_include_full_tracebacks_in_locations", before)


@pytest.fixture(scope="module")
def counted(full_op_names):
    return roofline.floors("planar_reach", "multimodal_bidal", 2, TINY)


def test_the_encoder_forward_counts_exactly_the_convs_useful_work(counted, full_op_names):
    """Every conv is lowered as a patch matmul, so the vision branch's dots hold its useful FLOPs, no zeros: per
    seed, the frames an update encodes times the hand-counted work of one frame."""
    text, _, config, _ = roofline.update_hlo("planar_reach", "multimodal_bidal", TINY)
    found = list(roofline.dots(text))
    vision = sum(d.flops for d in found if d.part == "encoder forward" and "VisionBranch" in d.op_name)
    frames = roofline.frames_encoded(found)
    assert frames == 2 * config.train.batch_size  # s_t and s_{t+1} (the online encoder)
    assert vision == frames * conv_flops(config.network.conv_channels, config.network.vision_features)
    assert counted["frames_per_seed"] == frames


def test_every_network_has_its_parts_flops_and_bytes(counted):
    parts = {p["part"]: p for p in counted["parts"]}
    assert list(parts)[: len(floor_table.PARTS)] == list(floor_table.PARTS)
    for name in ("encoder forward", "encoder backward", "critic", "actor", floor_table.MODELS):
        assert sum(parts[name]["flops"].values()) > 0, name
    n = sum(counted["parameters_per_seed"].values())
    assert parts["optimiser (Adam)"]["bytes"] == 2 * 7 * 4 * n  # 2 seeds, 7 words a parameter
    assert parts["encoder forward"]["bytes"] > 2 * counted["frames_per_seed"] * 42 * 42  # frames, then parameters


def test_each_part_is_set_against_its_own_floor():
    counted = {"parts": [{"part": "encoder forward", "flops": {"bf16": 989.4e6}, "bytes": 3.35e6},
                         {"part": "optimiser (Adam)", "flops": {}, "bytes": 6.7e6}]}
    measured = {"device_kind": "NVIDIA H100 80GB HBM3", "ms": 1.0,
                "parts": [{"component": "update: Encoder forward", "ms": 0.1},
                          {"component": "update: optimiser (Adam)", "ms": 0.02}, {"component": "other", "ms": 0.3}]}
    head, rows = floor_table.parts_table(counted, measured)
    assert "H100" in head[3]
    assert rows[0] == ["encoder forward", "0.99", "3.35", "1.0", "1.0", "100", "100×"]
    assert rows[1][-3:] == ["2.0", "20", "10×"]
    assert rows[2][0] == "other" and rows[2][-1] == "—"  # measured, with no floor counted
    assert rows[-1] == ["the update (wall time)", "", "", "1.0", "3.0", "1000", "333×"]


@pytest.mark.parametrize("component, part", [("update: Encoder backward", "encoder backward"),
                                             ("update: Encoder/VisionBranch_0/PatchConv_1 forward", "encoder forward"),
                                             ("update: InverseModel/Dense_0 backward", floor_table.MODELS),
                                             ("update: optimiser (Adam)", "optimiser (Adam)"), ("camera", "camera")])
def test_a_profile_label_at_any_depth_names_its_part(component, part):
    assert floor_table.part_of(component) == part


def test_an_unknown_chip_is_one_line():
    with pytest.raises(ValueError, match="'Tesla T4': no peaks known; one of H100, H200 is allowed"):
        floor_table.chip_of("Tesla T4")


def test_the_updates_bench_writes_its_rows_for_the_floors(tmp_path, capsys):
    path = tmp_path / "updates.json"
    bench_updates.main(["--env", "planar_reach", "--agent", "proprio_baseline", "--seeds", "1", "--updates", "2",
                        "--repeats", "1", "--variant", TINY, "--json", str(path)])
    [row] = json.loads(path.read_text())
    assert row["variant"] == TINY and row["ms"] > 0 and row["parts"] == [] and row["device_kind"]
