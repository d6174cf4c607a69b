"""Where a training program's compile time goes: trace, lowering to StableHLO, and XLA's compile (its HLO
passes and, on a GPU, LLVM/PTX code generation), for the main command's program and a NICOL image program.

    python -m experiments.bench.compile_time --out compile.json
    TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=gpu_compiler=1,nvptx_compiler=1 python -m experiments.bench.compile_time
    python -m experiments.bench.compile_time --programs main --xla-option xla_backend_optimization_level=0 --epoch

XLA's own phase timers (HLO passes, LLVM IR, PTX to SASS) print to stderr with the second form (on a CPU:
`TF_CPP_VMODULE=cpu_compiler=1`). JAX's persistent compilation cache is not used here: every figure is a cold XLA
compile in this process, of the programs as a run lowers them (`loop.short_source_locations`). `--xla-option
NAME=VALUE` passes XLA options to the epoch's compile (`Lowered.compile(compiler_options=...)`), and `--epoch` also
times one epoch of the compiled program, since an option that compiles sooner may run slower. `--parts` counts the
compiled epoch's HLO instructions by part of the epoch (physics, camera, each network's passes in the update, ...),
where its code, and much of its compile, goes; it keeps JAX's full source locations, whose op names carry the parts.
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import jax

from bidal_jax.run import loop
from experiments.bench.programs import seeded_program
from experiments.bench.tracing import instructions_by_component

PROGRAMS = {"main": ("ur5_reach", "multimodal_bidal", 1), "nicol": ("nicol_slide", "multimodal_bidal", 5)}


def xla_option(text: str) -> tuple[str, bool | int | float | str]:
    """"NAME=VALUE" -> (NAME, VALUE as a bool, int or float where it reads as one, else the text)."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"{text!r}: NAME=VALUE is allowed, e.g. xla_backend_optimization_level=1")
    try:
        return name, json.loads(value)
    except json.JSONDecodeError:
        return name, value


def stages(name: str, agent: str, seeds: int, backend: str, options: dict | None = None,
           epoch_too: bool = False, parts: bool = False) -> dict[str, Any]:
    """Seconds to build the env and the program, then to trace, lower and compile its init and epoch (the epoch
    with the XLA `options`), with `epoch_too` to run one epoch of it, and with `parts` the compiled epoch's HLO
    instructions by part of the epoch (`tracing.instructions_by_component`, as "epoch_instructions")."""
    times = {}
    start = time.perf_counter()
    init, epoch, *_ = seeded_program(name, agent, seeds, backend=backend)
    times["build_env_and_program"] = time.perf_counter() - start
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    for label, fn, args in (("init", init, (keys,)), ("epoch", epoch, None)):
        if args is None:
            args = (jax.eval_shape(init, keys),)
        t0 = time.perf_counter()
        traced = fn.trace(*args)
        t1 = time.perf_counter()
        lowered = traced.lower()
        t2 = time.perf_counter()
        compiled = lowered.compile(compiler_options=(options or None) if label == "epoch" else None)
        t3 = time.perf_counter()
        times.update({f"{label}_trace": t1 - t0, f"{label}_lower": t2 - t1, f"{label}_xla_compile": t3 - t2})
    if parts:
        times["epoch_instructions"] = dict(instructions_by_component(compiled.as_text()))
    if epoch_too:
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(init(keys))[1])
        times["epoch_run"] = time.perf_counter() - t0
    times["total"] = time.perf_counter() - start
    return times


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", default="jax", choices=["jax", "warp"])
    parser.add_argument("--out", default=None)
    parser.add_argument("--programs", nargs="+", default=list(PROGRAMS), choices=list(PROGRAMS))
    parser.add_argument("--xla-option", type=xla_option, action="append", default=[],
                        help="NAME=VALUE: an XLA option for the epoch's compile (repeatable)")
    parser.add_argument("--epoch", action="store_true", help="also run one epoch of the compiled program")
    parser.add_argument("--parts", action="store_true",
                        help="also count the compiled epoch's HLO instructions by part of the epoch; the parts are "
                        "read from the ops' full names, so the programs keep JAX's full source locations (as the "
                        "profiling benches lower them, not as a run does)")
    args = parser.parse_args(argv)
    if not args.parts:
        loop.short_source_locations()
    results = []
    options = dict(args.xla_option)
    for name, agent, seeds in (PROGRAMS[p] for p in args.programs):
        row = {"env": name, "agent": agent, "seeds": seeds, "backend": args.backend, "device": str(jax.devices()[0]),
               "xla_options": options, **stages(name, agent, seeds, args.backend, options, args.epoch, args.parts)}
        print(json.dumps(row), flush=True)
        results.append(row)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
