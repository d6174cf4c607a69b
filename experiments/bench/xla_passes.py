"""Where XLA's compile of a program goes, by HLO pass: the pass timers XLA logs with
`TF_CPP_MIN_LOG_LEVEL=0 TF_CPP_VMODULE=hlo_pass_pipeline=1`, summed per module and pass.

    python -m experiments.bench.xla_passes --out passes.log -- python -m experiments.bench.compile_time --programs main
    python -m experiments.bench.xla_passes --log passes.log --top 20

The first form runs a command with XLA's pass log on, keeps its stderr in `--out` and summarises it; the second
summarises a log written before. A pass's time is its own (exclusive): the passes and pipelines it runs inside it are
subtracted and counted for themselves, so a module's passes add up to its time in passes, and a pipeline's row holds
only what it does between its passes. A pass that compiles other modules inside it (on a GPU the autotuner, which
compiles and times candidate kernels of each fusion) counts their passes for those modules, which it may compile on
other threads at once; its own row keeps the rest (compiling candidates to machine code, running them). Code
generation after the passes (LLVM, PTX) is not a pass: XLA's compile time less the passes is that.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import os
import re
import subprocess
import sys

_LINE = re.compile(r"^\S+ \S+\s+(\d+) hlo_pass_pipeline\.cc:\d+\]\s(.*)$")  # thread id, message
_PIPELINE = re.compile(r"^Running HLO pass pipeline on module (\S+): (\S+)")
_START = re.compile(r"^\s+HLO pass (\S+)$")
_END = re.compile(r"^HLO pass: (\S+) time: [^(]*\((\d+) us\)")
LOG_ENV = {"TF_CPP_MIN_LOG_LEVEL": "0", "TF_CPP_VMODULE": "hlo_pass_pipeline=1"}


@dataclasses.dataclass
class _Open:
    """A pass running on a thread: its name, the module it runs on, the time its nested passes took, and the module
    of a pipeline started inside it (whose passes run on that module)."""

    name: str
    module: str
    nested_us: int = 0
    inner_module: str | None = None


def pass_times(lines) -> dict[str, collections.Counter]:
    """{module: Counter(pass -> exclusive microseconds)} from an XLA pass log's `lines` (`TF_CPP_VMODULE=
    hlo_pass_pipeline=1`). Each thread keeps a stack of open passes: a pass runs on the module of the innermost
    pipeline started inside an open pass, else on the module of the thread's last top-level pipeline."""
    times: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    stacks: dict[str, list[_Open]] = collections.defaultdict(list)
    base: dict[str, str] = {}
    for line in lines:
        if (match := _LINE.match(line)) is None:
            continue
        thread, message = match.groups()
        stack = stacks[thread]
        if (pipeline := _PIPELINE.match(message)) is not None:
            if stack:
                stack[-1].inner_module = pipeline.group(1)
            else:
                base[thread] = pipeline.group(1)
        elif (start := _START.match(message)) is not None:
            inner = next((p.inner_module for p in reversed(stack) if p.inner_module), None)
            stack.append(_Open(start.group(1), inner or base.get(thread, "?")))
        elif (end := _END.match(message)) is not None and stack and stack[-1].name == end.group(1):
            done, total = stack.pop(), int(end.group(2))
            times[done.module][done.name] += total - done.nested_us
            if stack:
                stack[-1].nested_us += total
    return times


def summary(times: dict[str, collections.Counter], top: int = 15, modules: int = 3) -> str:
    """The `modules` modules with the most time in passes, each with its `top` passes by exclusive seconds."""
    ranked = sorted(times.items(), key=lambda kv: -sum(kv[1].values()))
    out = []
    for module, passes in ranked[:modules]:
        out.append(f"{module}: {sum(passes.values()) / 1e6:.2f} s in passes")
        out += [f"  {us / 1e6:8.2f} s  {name}" for name, us in passes.most_common(top)]
    rest = ranked[modules:]
    if rest:
        out.append(f"{len(rest)} other modules: {sum(sum(p.values()) for _, p in rest) / 1e6:.2f} s in passes")
    return "\n".join(out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--log", help="summarise this pass log (written before)")
    parser.add_argument("--out", default="xla-passes.log", help="where the command's pass log goes")
    parser.add_argument("--top", type=int, default=15, help="passes shown per module")
    parser.add_argument("--modules", type=int, default=3, help="modules shown, most time in passes first")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- COMMAND ...: run it with the pass log on")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if bool(args.log) == bool(command):
        parser.error("give either --log FILE or -- COMMAND ..., e.g. -- python -m experiments.bench.compile_time")
    path = args.log
    if command:
        with open(args.out, "w") as log:
            code = subprocess.run(command, stderr=log, env={**os.environ, **LOG_ENV}).returncode
        if code:
            sys.exit(f"{' '.join(command)} failed (exit {code}); its stderr is in {args.out}")
        path = args.out
    try:
        with open(path, errors="replace") as lines:
            print(summary(pass_times(lines), args.top, args.modules))
    except OSError as err:
        sys.exit(f"cannot read the pass log {path}: {err.strerror or err}")


if __name__ == "__main__":
    main()
