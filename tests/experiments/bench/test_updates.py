"""experiments.bench.updates: the updates-only program runs the learner's updates on a full buffer; option checks."""

import jax
import numpy as np
import pytest

from experiments.bench import tracing
from experiments.bench import updates as bench_updates

TINY = "batch_size=8,buffer_episodes=32,num_envs=16,net.hidden_size=16,net.embed_size=8"


def test_the_program_runs_the_asked_updates_of_every_seed_on_a_full_buffer():
    compiled, ts, keys, compile_s = bench_updates.update_program("planar_reach", "proprio_baseline", 2, 3, TINY)
    assert compile_s > 0
    np.testing.assert_array_equal(ts.buffer.size, [32, 32])  # batches are drawn from every slot
    after, metrics = compiled(ts, keys)
    np.testing.assert_array_equal(after.updates, [3, 3])
    assert jax.tree.leaves(metrics)[0].shape[:2] == (2, 3)  # [seeds, updates]


@pytest.fixture
def full_op_names():
    """Programs compiled here with JAX's full source locations, whose op_names carry the scopes, and not read from
    the persistent compilation cache: its key leaves the locations out, so an entry that a run in this process or
    an earlier one compiled with short locations (`loop.short_source_locations`) would come back with short names."""
    before = jax.config.jax_include_full_tracebacks_in_locations, jax.config.jax_enable_compilation_cache
    jax.config.update("jax_include_full_tracebacks_in_locations", True)
    jax.config.update("jax_enable_compilation_cache", False)
    yield
    jax.config.update("jax_include_full_tracebacks_in_locations", before[0])
    jax.config.update("jax_enable_compilation_cache", before[1])


def test_the_compiled_update_names_its_parts_for_the_profile(full_op_names):
    """The learner's `jax.named_scope`s reach the compiled program, so that `tracing.by_component` can attribute its
    kernels: every part of a BidAL image agent's update is found among its instructions' op_names."""
    compiled, *_ = bench_updates.update_program("planar_reach", "multimodal_bidal", 1, 1, TINY + ",net.conv_channels=2")
    parts = {tracing.component(op) for op in tracing.op_names(compiled.as_text()).values()}
    assert {f"update: {network} {direction}" for network in tracing.NETWORKS for direction in ("forward", "backward")
            } | {"update: optimiser (Adam)", "update: target networks (Polyak)", "update: replay and HER sampling"
                 } <= parts


def test_kernels_per_update_reads_the_busiest_device_stream():
    trace = [{"process": "/host:CPU", "events": 900}, {"process": "/device:GPU:0", "events": 500},
             {"process": "/device:GPU:0", "events": 40}]
    assert bench_updates.kernels_per_update(trace, 100) == 5.0
    assert bench_updates.kernels_per_update(trace[:1], 100) is None


@pytest.mark.parametrize("args, message", [(["--updates", "0"], "--updates 0"), (["--repeats", "-1"], "--repeats -1"),
                                           (["--seeds", "0"], "seeds"), (["--depth", "-1"], "--depth -1")])
def test_bad_counts_stop_with_one_line(args, message, capsys):
    with pytest.raises(SystemExit) as stop:
        bench_updates.main(args)
    assert message in str(stop.value) and "\n" not in str(stop.value)
