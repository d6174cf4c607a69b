"""experiments.bench.xla_passes: XLA's pass log summed by module and pass, each pass's own time."""

import sys

import pytest

from experiments.bench import xla_passes


def _line(thread: int, message: str) -> str:
    return f"I1127 08:51:00.954681   {thread} hlo_pass_pipeline.cc:211] {message}"


def _ran(thread: int, name: str, us: int) -> list[str]:
    return [_line(thread, f"  HLO pass {name}"), _line(thread, f"HLO pass: {name} time: {us} us ({us} us)")]


LOG = [
    _line(1, "Running HLO pass pipeline on module main_module: optimization"),
    *_ran(1, "algsimp", 10),
    _line(1, "  HLO pass simplification"),  # a pipeline run as a pass: its passes are its own rows
    _line(1, "Running HLO pass pipeline on module main_module: simplification"),
    *_ran(1, "dce", 20),
    *_ran(1, "cse", 30),
    _line(1, "HLO pass: simplification time: 70 us (70 us)"),
    _line(1, "  HLO pass autotuner"),  # compiles a candidate module inside it
    _line(1, "Running HLO pass pipeline on module candidate: rewriter"),
    *_ran(1, "gemm-rewriter", 5),
    _line(1, "HLO pass: autotuner time: 1.2 ms (1200 us) (cumulative: 1.3 ms)"),
    *_ran(1, "copy-insertion", 7),  # after the candidate's pipeline: the main module's again
    _line(2, "Running HLO pass pipeline on module other: optimization"),
    *_ran(2, "dce", 3),
    "I1127 08:51:00.954681   1 cpu_compiler.cc:1] not a pass line",
]


def test_each_pass_counts_its_own_time_for_the_module_it_ran_on():
    times = xla_passes.pass_times(LOG)
    assert dict(times["main_module"]) == {"algsimp": 10, "simplification": 20, "dce": 20, "cse": 30,
                                          "autotuner": 1195, "copy-insertion": 7}
    assert dict(times["candidate"]) == {"gemm-rewriter": 5}
    assert dict(times["other"]) == {"dce": 3}
    text = xla_passes.summary(times, top=2, modules=1)
    assert text.splitlines() == ["main_module: 0.00 s in passes", "      0.00 s  autotuner", "      0.00 s  cse",
                                 "2 other modules: 0.00 s in passes"]


def test_a_real_compile_log_names_its_modules_passes(tmp_path):
    """XLA's own log of a small program's compile: its module's passes, none of them negative."""
    log = tmp_path / "passes.log"
    code = ("import jax, jax.numpy as jnp; "
            "jax.jit(lambda x: jnp.sin(x) @ x.T).lower(jnp.ones((8, 8))).compile()")
    xla_passes.main(["--out", str(log), "--", sys.executable, "-c", code])
    times = xla_passes.pass_times(log.read_text().splitlines())
    module = next(m for m in times if "lambda" in m)
    assert {"algsimp", "layout-assignment"} <= set(times[module])
    assert all(us >= 0 for us in times[module].values())


def test_a_missing_log_or_both_inputs_are_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit, match="cannot read the pass log"):
        xla_passes.main(["--log", str(tmp_path / "none.log")])
    with pytest.raises(SystemExit):
        xla_passes.main(["--log", "x.log", "--", "true"])
    assert "either --log FILE or -- COMMAND" in capsys.readouterr().err

