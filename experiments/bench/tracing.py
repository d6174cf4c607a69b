"""A JAX profiler trace of one call, summarised per device stream and host thread and per part of the program
(the benchmarks' shared part).

`traced(fn, out)` runs `fn` once under `jax.profiler.trace` (the trace, with a Perfetto JSON copy, stays in
`out` for TensorBoard or ui.perfetto.dev) and returns its wall seconds and `summarise` of the trace: per stream
or thread, the seconds its events add up to, how many there are and its largest operations. On a GPU the event
count of the compute stream is the number of kernels the call launched.

Given the compiled program's HLO text, `traced` also attributes each device event to a part of the epoch
(`component`): XLA names a kernel after its fused instruction, whose metadata keeps the `jax.named_scope`s it was
traced under (`bidal_jax.train.UPDATE_SCOPE` and the others, the env's physics and camera, the Flax modules of
the networks, `transpose(...)` for a backward pass). A fusion carries the scopes of one of the operations it
fused, so a kernel that fuses the end of one part with the start of the next counts for one of them. A program
lowered after `loop.short_source_locations` (as a run's are) has lost those scopes: profile a bench's program.
"""

from __future__ import annotations

import collections
import functools
import glob
import gzip
import json
import os
import re
import time
from typing import Any, Callable, Iterator

import jax

from bidal_jax import acting, networks, train
from envs_mjx.base import CAMERA_SCOPE, PHYSICS_SCOPE

NETWORKS = tuple(cls.__name__ for cls in (networks.Encoder, networks.Critic, networks.Actor, networks.ForwardModel,
                                          networks.InverseModel))  # the Flax modules' scopes in an op's name
# parts of the update, then of the rest of the epoch, by the scope that marks them (the first found counts)
UPDATE_PARTS = ((train.REPLAY_SCOPE, "replay and HER sampling"), (train.OPTIMISER_SCOPE, "optimiser (Adam)"),
                (train.TARGET_SCOPE, "target networks (Polyak)"))
EPOCH_PARTS = ((PHYSICS_SCOPE, "physics"), (CAMERA_SCOPE, "camera"), (acting.ACTING_SCOPE, "policy in rollouts"),
               (train.REPLAY_SCOPE, "replay insert"), (train.NORMALISER_SCOPE, "normalisers"))
GPU_EVENTS = 16_000_000  # device events a trace keeps (`profile_options`); a NICOL image epoch launches ~3 M
_COMPUTATION = re.compile(r"^(?:ENTRY\s+)?%([\w.\-]+)\s.*\{\s*$")
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%([\w.\-]+)\s*=\s*(.*)$")
_OP_NAME, _CALLS = re.compile(r'op_name="([^"]*)"'), re.compile(r"calls=%([\w.\-]+)")
_OPERAND = re.compile(r"%([\w.\-]+)")


def kernel_name(instruction: str) -> str:
    """The name XLA gives the GPU kernel of an HLO instruction ("loop_add_fusion.3" -> "loop_add_fusion_3")."""
    return re.sub(r"[.\-]", "_", instruction)


def _instructions(hlo_text: str) -> Iterator[tuple[str | None, str, str]]:
    """(computation, instruction name, the rest of its line) of each instruction of a module's HLO text."""
    computation = None
    for line in hlo_text.splitlines():
        if (header := _COMPUTATION.match(line)) is not None:
            computation = header.group(1)
        elif (instruction := _INSTRUCTION.match(line)) is not None:
            yield computation, *instruction.groups()


def op_names(hlo_text: str) -> dict[str, str]:
    """{kernel name: op_name} of the instructions of a compiled module's HLO text. An instruction XLA made without
    an op_name (a multi-output fusion, a concatenation it merged) takes the first op_name inside the computation
    it calls, else that of the nearest instruction it reads (followed back through operands without one)."""
    own, calls, operands, first_in = {}, {}, {}, {}
    for computation, name, rest in _instructions(hlo_text):
        body, _, metadata = rest.partition("metadata=")
        if (op := _OP_NAME.search(metadata)) is not None:
            own[name] = op.group(1)
            first_in.setdefault(computation, op.group(1))
        if (called := _CALLS.search(body)) is not None:
            calls[name] = called.group(1)
        operands[name] = _OPERAND.findall(body.split("calls=")[0])

    def resolve(name: str, hops: int = 8) -> str | None:
        """The op_name of `name`, else of the nearest instruction it reads within `hops` operands."""
        frontier, seen = [name], {name}
        for _ in range(hops):
            for each in frontier:
                if each in own:
                    return own[each]
                if calls.get(each) in first_in:
                    return first_in[calls[each]]
            frontier = [o for each in frontier for o in operands.get(each, ()) if o not in seen and not seen.add(o)]
        return None

    return {kernel_name(name): op for name in operands for op in [resolve(name)] if op is not None}


def shared_kernels(hlo_text: str) -> dict[str, list[str]]:
    """{kernel name: the kernel names of every fusion alike to it, itself included} for the fusions of a compiled
    module's HLO text that have a twin: the same result shape and the same fused computation, its instructions'
    names and metadata aside. XLA's GPU backend compiles such fusions once and launches each under the first one's
    kernel name, and a kernel inside a CUDA graph carries no other name in a trace; so a kernel of the rollout's
    policy pass and its twin in the updates (the target encoder on s_{t+1} has the policy's batch) are one name."""
    bodies, fusions = collections.defaultdict(list), {}
    for computation, name, rest in _instructions(hlo_text):
        body = _OPERAND.sub("%", rest.split(", metadata=")[0].split(", backend_config=")[0])
        bodies[computation].append(body)
        if (called := _CALLS.search(rest)) is not None and " fusion(" in f" {rest}":
            fusions[name] = (rest.split(" fusion(")[0], called.group(1))
    twins = collections.defaultdict(list)
    for name, (shape, called) in fusions.items():
        twins[(shape, tuple(bodies[called]))].append(kernel_name(name))
    return {kernel: group for group in twins.values() if len(group) > 1 for kernel in group}


def component(op_name: str, depth: int = 0) -> str:
    """The part of a training epoch an operation belongs to, by the scopes in its `op_name`
    ("jit(epoch)/.../update/vmap(transpose(jvp(Encoder)))/VisionBranch_0/PatchConv_1/..." -> "update: Encoder
    backward"); with `depth` d, a network's part names its first d submodules too ("update: Encoder/VisionBranch_0/
    PatchConv_1 backward" for d = 2)."""
    scopes = [re.sub(r"^(?:\w+\()+|\)+$", "", part) for part in op_name.split("/")]  # transforms stripped
    if train.EVALUATION_SCOPE in scopes:
        return "evaluation"
    if train.UPDATE_SCOPE in scopes:
        part = next((label for scope, label in UPDATE_PARTS if scope in scopes), None)
        at = next((i for i, scope in enumerate(scopes) if scope in NETWORKS), None)
        if part is None and at is not None:
            module = "/".join(scopes[at : at + 1 + depth])
            part = f"{module} {'backward' if 'transpose(' in op_name else 'forward'}"
        return f"update: {part or 'losses and the rest'}"
    return next((label for scope, label in EPOCH_PARTS if scope in scopes), "other")


def instructions_by_component(hlo_text: str) -> list[tuple[str, int]]:
    """(part, instructions) of a compiled module's HLO text, most first: each instruction with an op_name of its
    own or inherited (`op_names`), those inside fusions too, counted for its `component`. Where a program's code
    goes, and with it much of its compile (`experiments.bench.compile_time --parts`)."""
    return collections.Counter(component(op) for op in op_names(hlo_text).values()).most_common()


def by_component(events: list[dict], names: dict[str, str], depth: int = 0,
                 shared: dict[str, list[str]] | None = None) -> list[dict]:
    """A trace's operations per `component(..., depth)` of their op_name in `names` (`op_names`): rows of {component,
    seconds, events, inherited, top: its 2 largest kernels as (name, share of its seconds)}, largest first. On a
    GPU the operations are the device's events. A kernel found by neither its name nor its "hlo_op" argument (a
    library's kernel inside a CUDA graph, such as cuBLAS's `nvjet_*` matmuls, which carry no HLO name there) counts
    for the part of the last attributed kernel before it on its stream (`inherited` counts those); a copy or
    memset so found, or a kernel with none before it, is "unattributed". A kernel that twin fusions of several parts
    share (`shared`, from `shared_kernels`) counts for the twin's part that the kernel before it on its stream has,
    else for the twin's on the same side of the updates (an update's part, or not), else for its name's. On a CPU the
    operations are the host's events of an HLO instruction (an "hlo_op" argument), less control flow (a loop's event
    spans its body's)."""
    devices = {pid for (pid, tid), name in _names(events).items() if tid is None and name.startswith("/device:")}

    def counted(e: dict) -> bool:
        if devices:
            return e["pid"] in devices
        return not e.get("args", {}).get("hlo_op", "while").startswith(("while", "conditional", "call"))

    part_of = functools.cache(lambda op: component(op, depth))  # a trace launches each kernel many times

    def own(e: dict) -> str | None:
        op = names.get(kernel_name(e["name"])) or names.get(kernel_name(e.get("args", {}).get("hlo_op", "")))
        return part_of(op) if op else None

    # each shared kernel's twins' parts where they differ, worked out once rather than at each of its launches
    twin_parts = {kernel: sorted(found) for kernel, group in (shared or {}).items()
                  for found in [{part_of(names[k]) for k in group if k in names}] if len(found) > 1}

    def twin(e: dict, part: str | None, last: str | None) -> str | None:
        """`part`, or where the kernel is shared by fusions of several parts, the twin's part that fits `last`."""
        twins = twin_parts.get(kernel_name(e["name"]))
        if twins is None or last is None:
            return part
        if last in twins:
            return last
        side = [p for p in twins if p.startswith("update:") == last.startswith("update:")]
        return side[0] if len(side) == 1 else part

    ordered = sorted(filter(counted, _complete(events)), key=lambda e: (e["pid"], e.get("tid"), e.get("ts", 0)))
    parts, before, inherited = {}, {}, collections.Counter()
    for e in ordered:
        stream = (e["pid"], e.get("tid"))
        part = twin(e, own(e), before.get(stream))
        if part is None and stream in before and not e["name"].startswith(("Memcpy", "Memset")):
            part = before[stream]
            inherited[part] += 1
        if part is not None:
            before[stream] = part
        parts[id(e)] = part or "unattributed"
    return [{"component": key, "seconds": s, "events": n, "inherited": inherited[key],
             "top": [(name, t / max(s, 1e-12)) for name, t in by_name.most_common(2)]}
            for key, s, n, by_name in _tally(lambda e: parts[id(e)], ordered)]


def _names(events: list[dict]) -> dict[tuple, str]:
    """The names a trace's metadata gives its processes, {(pid, None): name}, and threads, {(pid, tid): name}."""
    return {(e["pid"], e["tid"] if e["name"] == "thread_name" else None): e["args"]["name"] for e in events
            if e.get("ph") == "M" and e.get("name") in ("process_name", "thread_name")}


def _complete(events: list[dict]) -> list[dict]:
    """A trace's complete ("X") events: those with a duration."""
    return [e for e in events if e.get("ph") == "X"]


def _tally(key: Callable[[dict], Any], events: Any) -> list[tuple[Any, float, int, collections.Counter]]:
    """(key, the seconds its events add up to, their count, their seconds by event name) per `key(event)` of
    `events`, largest total first."""
    seconds, count = collections.Counter(), collections.Counter()
    by_name = collections.defaultdict(collections.Counter)
    for e in events:
        k = key(e)
        seconds[k] += e.get("dur", 0) / 1e6
        count[k] += 1
        by_name[k][e["name"]] += e.get("dur", 0) / 1e6
    return [(k, s, count[k], by_name[k]) for k, s in seconds.most_common()]


def summarise(events: list[dict], top: int = 10) -> list[dict]:
    """Per (process, thread) of a Chrome/Perfetto trace's complete ("X") events: the seconds they
    add up to, their count and the `top` names by seconds; largest total first."""
    names = _names(events)

    def where(e: dict) -> tuple[str, str]:
        return names.get((e["pid"], None), str(e["pid"])), names.get((e["pid"], e["tid"]), str(e["tid"]))

    return [{"process": p, "thread": t, "seconds": s, "events": n, "top": by_name.most_common(top)}
            for (p, t), s, n, by_name in _tally(where, _complete(events))]


def profile_options(events: int = GPU_EVENTS) -> jax.profiler.ProfileOptions:
    """The profiler's options with room for `events` GPU kernel events and API callbacks (the profiler's own
    limit, about 2 million, drops the rest: the end of a NICOL image epoch, its evaluation included)."""
    options = jax.profiler.ProfileOptions()
    options.advanced_configuration = {"gpu_max_activity_api_events": events, "gpu_max_callback_api_events": events}
    return options


def traced(fn: Callable[[], Any], out: str, top: int = 10, hlo_text: str = "",
           depth: int = 0) -> tuple[float, list[dict], list[dict]]:
    """(wall seconds of `fn()` until its result is ready, `summarise(..., top)` of its trace written to `out`,
    `by_component(..., depth)` of its device events given the HLO text of the program `fn` runs, which then goes to
    `out`/program.hlo.txt; [] without)."""
    with jax.profiler.trace(out, create_perfetto_trace=True, profiler_options=profile_options()):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        wall = time.perf_counter() - start
    newest = max(glob.glob(os.path.join(out, "**", "perfetto_trace.json.gz"), recursive=True), key=os.path.getmtime)
    with gzip.open(newest) as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    if not hlo_text:
        return wall, summarise(events, top), []
    with open(os.path.join(out, "program.hlo.txt"), "w") as f:  # what the kernels' names refer to
        f.write(hlo_text)
    return wall, summarise(events, top), by_component(events, op_names(hlo_text), depth, shared_kernels(hlo_text))


def print_components(rows: list[dict], wall: float, unit: str = "s") -> None:
    """A markdown table of `by_component`'s rows (their seconds and events in `unit`s, e.g. per update):
    the device's time, its share of all device events' time, events."""
    total = sum(r["seconds"] for r in rows)
    print(f"\ntime by part of the program: {total:.3f} {unit} of the device's operations in {wall:.3f} {unit} of "
          "wall time\n")
    print(f"| part | device {unit} | share | events | largest kernels |")
    print("| --- | --- | --- | --- | --- |")
    for r in rows:
        largest = ", ".join(f"{name[:48]} {share:.0%}" for name, share in r["top"])
        events = f"{r['events']:,.0f}" + (f" ({r['inherited']:,.0f} by the kernel before)" if r["inherited"] else "")
        print(f"| {r['component']} | {r['seconds']:.3f} | {r['seconds'] / max(total, 1e-12):.1%} "
              f"| {events} | {largest} |")


def print_summary(rows: list[dict], streams: int) -> None:
    """Print the `streams` largest streams or threads of `summarise`'s rows with their largest operations."""
    for row in rows[:streams]:
        print(f"\n{row['process']} / {row['thread']}: {row['seconds']:.3f} s in {row['events']:,} events")
        for op, seconds in row["top"]:
            print(f"  {seconds:8.3f} s  {op[:100]}")
