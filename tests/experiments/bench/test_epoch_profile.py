"""experiments.bench.epoch_profile (and throughput): their option checks; experiments.bench.tracing: the trace
summary (a synthetic trace) and the attribution of kernels to the parts of an epoch (synthetic HLO text and
traces)."""

import pytest

from experiments.bench import epoch_profile as bench_profile
from experiments.bench import tracing


def test_summarise_groups_by_stream_counts_events_and_ranks_operations():
    events = [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "name": "thread_name", "pid": 1, "tid": 7, "args": {"name": "Stream #14(Compute)"}},
        {"ph": "X", "pid": 1, "tid": 7, "name": "fusion_a", "dur": 3.0},
        {"ph": "X", "pid": 1, "tid": 7, "name": "fusion_b", "dur": 5.0},
        {"ph": "X", "pid": 1, "tid": 7, "name": "fusion_a", "dur": 4.0},
        {"ph": "X", "pid": 2, "tid": 1, "name": "host_op", "dur": 1.0},  # no names: ids stand in
        {"ph": "i", "pid": 1, "tid": 7, "name": "instant"},  # not a complete event
    ]
    rows = tracing.summarise(events, top=1)
    assert [(r["process"], r["thread"], r["events"]) for r in rows] == [
        ("/device:GPU:0", "Stream #14(Compute)", 3),
        ("2", "1", 1),
    ]
    assert rows[0]["seconds"] == pytest.approx(12e-6)
    assert rows[0]["top"] == [("fusion_a", pytest.approx(7e-6))]


def test_bad_seed_count_is_a_one_line_error():
    with pytest.raises(SystemExit, match="--seeds 0: must be a positive integer"):
        bench_profile.main(["--seeds", "0"])


HLO = """\
%fused_concatenate.11 (param_0.1: bf16[2,3]) -> bf16[2,6] {
  %param_0.1 = bf16[2,3]{1,0} parameter(0), metadata={scheduling_name="param_0.1"}
  ROOT %concatenate.4 = bf16[2,6]{1,0} concatenate(%param_0.1, %param_0.1), dimensions={1}
}

%fused_add (p: f32[2]) -> f32[2] {
  %p = f32[2]{0} parameter(0)
  ROOT %add.1 = f32[2]{0} add(%p, %p), metadata={op_name="jit(epoch)/while/body/update/optimiser/add"}
}

ENTRY %main.5 (a: bf16[2,3], b: f32[2]) -> bf16[2,6] {
  %a = bf16[2,3]{1,0} parameter(0)
  %gemm_fusion_dot.84 = bf16[2,3]{1,0} fusion(%a), kind=kCustom, metadata={op_name="{ENCODER}"}
  %gte.2 = bf16[2,3]{1,0} get-tuple-element(%gemm_fusion_dot.84), index=0
  %input_concatenate_fusion.7 = bf16[2,6]{1,0} fusion(%gte.2), calls=%fused_concatenate.11, metadata={x="y"}
  %loop_add_fusion = f32[2]{0} fusion(%b), kind=kLoop, calls=%fused_add
  ROOT %copy.1 = bf16[2,6]{1,0} copy(%input_concatenate_fusion.7), metadata={op_name="jit(epoch)/physics/copy"}
}
""".replace("{ENCODER}", "jit(epoch)/update/vmap(transpose(jvp(Encoder)))/VisionBranch_0/PatchConv_1/dot_general")


def test_kernels_are_named_after_their_instructions_and_inherit_a_missing_op_name():
    names = tracing.op_names(HLO)
    assert names["gemm_fusion_dot_84"].endswith("PatchConv_1/dot_general")
    assert names["loop_add_fusion"].endswith("update/optimiser/add")  # from inside the computation it calls
    assert names["input_concatenate_fusion_7"] == names["gemm_fusion_dot_84"]  # from the fusion it reads, via a GTE
    assert "a" not in names  # a parameter with no op_name anywhere behind it


@pytest.mark.parametrize("op_name, part", [
    ("jit(epoch)/while/body/update/vmap(transpose(jvp(Encoder)))/VisionBranch_0/PatchConv_1/dot_general",
     "update: Encoder backward"),
    ("jit(epoch)/while/body/update/vmap(jvp(Critic))/Dense_0/dot_general", "update: Critic forward"),
    ("jit(epoch)/while/body/update/optimiser/Encoder/add", "update: optimiser (Adam)"),
    ("jit(epoch)/while/body/update/replay/gather", "update: replay and HER sampling"),
    ("jit(epoch)/while/body/update/mul", "update: losses and the rest"),
    ("jit(epoch)/while/body/vmap(physics)/while/body/mul", "physics"),
    ("jit(epoch)/while/body/camera/reduce_max", "camera"),
    ("jit(epoch)/while/body/acting/Encoder/VisionBranch_0/dot_general", "policy in rollouts"),
    ("jit(epoch)/evaluation/while/body/physics/mul", "evaluation"),
    ("jit(epoch)/add", "other"),
])
def test_each_operation_counts_for_the_part_its_scopes_name(op_name, part):
    assert tracing.component(op_name) == part


def test_a_depth_names_the_networks_submodules():
    op = "jit(epoch)/update/vmap(transpose(jvp(Encoder)))/VisionBranch_0/PatchConv_1/dot_general"
    assert tracing.component(op, depth=2) == "update: Encoder/VisionBranch_0/PatchConv_1 backward"
    assert tracing.component("jit(epoch)/update/optimiser/Encoder/add", depth=2) == "update: optimiser (Adam)"


def test_device_events_add_up_by_part_and_a_library_kernel_by_its_hlo_op():
    names = tracing.op_names(HLO)
    events = [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
        {"ph": "M", "name": "process_name", "pid": 2, "args": {"name": "/host:CPU"}},
        {"ph": "X", "pid": 1, "tid": 7, "name": "gemm_fusion_dot_84", "dur": 3.0},
        {"ph": "X", "pid": 1, "tid": 7, "name": "input_concatenate_fusion_7", "dur": 1.0},
        {"ph": "X", "pid": 1, "tid": 7, "name": "sm90_xmma_gemm", "dur": 2.0, "args": {"hlo_op": "copy.1"}},
        {"ph": "X", "pid": 1, "tid": 7, "name": "MemcpyD2D", "dur": 5.0},
        {"ph": "X", "pid": 2, "tid": 1, "name": "gemm_fusion_dot_84", "dur": 9.0},  # the host's: not counted
    ]
    rows = {r["component"]: r for r in tracing.by_component(events, names)}
    assert set(rows) == {"update: Encoder backward", "physics", "unattributed"}
    assert rows["update: Encoder backward"]["seconds"] == pytest.approx(4e-6)
    assert rows["update: Encoder backward"]["events"] == 2
    assert rows["update: Encoder backward"]["top"][0] == ("gemm_fusion_dot_84", pytest.approx(0.75))
    assert rows["physics"]["seconds"] == pytest.approx(2e-6)
    assert rows["unattributed"]["seconds"] == pytest.approx(5e-6)


def test_a_library_kernel_without_a_name_counts_for_the_kernel_before_it_on_its_stream():
    """cuBLAS's kernels in a CUDA graph carry no HLO name: such a kernel counts for the part of the kernel launched
    before it on its stream; a copy, or a kernel first on its stream, stays unattributed."""
    names = tracing.op_names(HLO)
    events = [
        {"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
        {"ph": "X", "pid": 1, "tid": 8, "ts": 0.0, "name": "nvjet_sm90_tst_64x256", "dur": 7.0},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 3.0, "name": "nvjet_sm90_tst_160x128", "dur": 2.0},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 1.0, "name": "gemm_fusion_dot_84", "dur": 2.0},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 5.0, "name": "MemcpyD2D", "dur": 5.0},
        {"ph": "X", "pid": 1, "tid": 7, "ts": 10.0, "name": "nvjet_sm90_tst_160x128", "dur": 1.0},
    ]
    rows = {r["component"]: r for r in tracing.by_component(events, names)}
    assert rows["update: Encoder backward"]["events"] == 3 and rows["update: Encoder backward"]["inherited"] == 2
    assert rows["update: Encoder backward"]["seconds"] == pytest.approx(5e-6)
    assert rows["unattributed"]["events"] == 2 and rows["unattributed"]["seconds"] == pytest.approx(12e-6)


def test_on_a_cpu_host_operations_count_less_control_flow():
    names = {"add_fusion_1": "jit(epoch)/update/optimiser/add", "while_3": "jit(epoch)/update/while"}
    events = [
        {"ph": "X", "pid": 2, "tid": 1, "name": "add_fusion.1", "dur": 2.0, "args": {"hlo_op": "add_fusion.1"}},
        {"ph": "X", "pid": 2, "tid": 1, "name": "while.3", "dur": 9.0, "args": {"hlo_op": "while.3"}},
        {"ph": "X", "pid": 2, "tid": 1, "name": "ThunkExecutor::Execute", "dur": 9.0},
    ]
    assert [(r["component"], r["events"]) for r in tracing.by_component(events, names)] == [
        ("update: optimiser (Adam)", 1)]


def test_a_compiled_programs_instructions_count_for_their_parts():
    """Every instruction with an op_name, its own or inherited, inside fusions too; those without none."""
    assert tracing.instructions_by_component(HLO) == [("update: Encoder backward", 3),
                                                      ("update: optimiser (Adam)", 2), ("physics", 1)]


TWINS = """\
%fused_pad.1 (p: bf16[5,8]) -> bf16[5,9] {
  %p = bf16[5,8]{1,0} parameter(0)
  %c = bf16[] constant(0)
  ROOT %pad.1 = bf16[5,9]{1,0} pad(%p, %c), padding=0_0x0_1, metadata={op_name="{ACT}"}
}

%fused_pad.2 (q: bf16[5,8]) -> bf16[5,9] {
  %q = bf16[5,8]{1,0} parameter(0)
  %d = bf16[] constant(0)
  ROOT %pad.2 = bf16[5,9]{1,0} pad(%q, %d), padding=0_0x0_1, metadata={op_name="{ENC}"}
}

%fused_pad.3 (r: bf16[5,8]) -> bf16[5,9] {
  %r = bf16[5,8]{1,0} parameter(0)
  %e = bf16[] constant(1)
  ROOT %pad.3 = bf16[5,9]{1,0} pad(%r, %e), padding=0_0x0_1, metadata={op_name="{CAM}"}
}

ENTRY %main (a: bf16[5,8]) -> bf16[5,9] {
  %a = bf16[5,8]{1,0} parameter(0)
  %loop_pad_fusion.1 = bf16[5,9]{1,0} fusion(%a), calls=%fused_pad.1, metadata={op_name="{ACT}"}
  %loop_pad_fusion.2 = bf16[5,9]{1,0} fusion(%a), calls=%fused_pad.2, metadata={op_name="{ENC}"}
  %loop_pad_fusion.3 = bf16[5,9]{1,0} fusion(%a), calls=%fused_pad.3, metadata={op_name="{CAM}"}
  %gemm_fusion_dot.4 = bf16[5,9]{1,0} fusion(%a), kind=kCustom, metadata={op_name="{CRITIC}"}
  ROOT %t = bf16[5,9]{1,0} tuple(%loop_pad_fusion.1)
}
""".replace("{ACT}", "jit(epoch)/while/body/acting/Encoder/pad").replace(
    "{ENC}", "jit(epoch)/update/jvp(Encoder)/pad").replace("{CAM}", "jit(epoch)/camera/pad").replace(
    "{CRITIC}", "jit(epoch)/update/jvp(Critic)/dot")


def test_twin_fusions_share_a_kernel_and_count_for_the_part_around_them():
    """XLA compiles alike fusions once and launches each under the first one's kernel name: the rollout policy's
    pad and the update encoder's (same shape and computation, names aside) are one kernel, the camera's pad of
    another constant is not; each launch counts for the twin's part its neighbours name."""
    shared = tracing.shared_kernels(TWINS)
    assert shared == {"loop_pad_fusion_1": ["loop_pad_fusion_1", "loop_pad_fusion_2"],
                      "loop_pad_fusion_2": ["loop_pad_fusion_1", "loop_pad_fusion_2"]}
    names = tracing.op_names(TWINS)
    events = [{"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}}] + [
        {"ph": "X", "pid": 1, "tid": 7, "ts": float(i), "name": name, "dur": 1.0}
        for i, name in enumerate(["loop_pad_fusion_3", "loop_pad_fusion_1",  # a rollout: camera, then the policy
                                  "gemm_fusion_dot_4", "loop_pad_fusion_1",  # an update: critic, then the encoder
                                  "loop_pad_fusion_1"])]  # after the update's: still the update's
    rows = {r["component"]: r["events"] for r in tracing.by_component(events, names, shared=shared)}
    assert rows == {"camera": 1, "policy in rollouts": 1, "update: Critic forward": 1, "update: Encoder forward": 2}
    # without the twins every launch counts for the name's part
    rows = {r["component"]: r["events"] for r in tracing.by_component(events, names)}
    assert rows["policy in rollouts"] == 3


def test_an_engine_these_devices_cannot_run_is_a_one_line_error():
    from experiments.bench import throughput

    for main, args in ((bench_profile.main, ["--physics", "warp"]),
                       (throughput.main, ["--devices", "1", "--seeds", "1", "--physics", "warp"])):
        with pytest.raises(SystemExit, match=r"^error: --physics warp needs NVIDIA GPUs and warp-lang: this run "
                                             r"lays out 1 cpu device\(s\); allowed here: jax, auto$"):
            main(args)
