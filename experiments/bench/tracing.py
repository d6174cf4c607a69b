"""A JAX profiler trace of one call, summarised per device stream and host thread (the benchmarks' shared part).

`traced(fn, out)` runs `fn` once under `jax.profiler.trace` (the trace, with a Perfetto JSON copy, stays in
`out` for TensorBoard or ui.perfetto.dev) and returns its wall seconds and `summarise` of the trace: per stream
or thread, the seconds its events add up to, how many there are and its largest operations. On a GPU the event
count of the compute stream is the number of kernels the call launched.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import os
import time
from typing import Any, Callable

import jax


def summarise(events: list[dict], top: int = 10) -> list[dict]:
    """Per (process, thread) of a Chrome/Perfetto trace's complete ("X") events: the seconds they
    add up to, their count and the `top` names by seconds; largest total first."""
    names = {
        (e["pid"], None): e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"
    }
    names.update(
        {
            (e["pid"], e["tid"]): e["args"]["name"]
            for e in events
            if e.get("ph") == "M" and e.get("name") == "thread_name"
        }
    )
    seconds, count = collections.Counter(), collections.Counter()
    by_name = collections.defaultdict(collections.Counter)
    for e in events:
        if e.get("ph") != "X":
            continue
        where = (names.get((e["pid"], None), str(e["pid"])), names.get((e["pid"], e["tid"]), str(e["tid"])))
        seconds[where] += e.get("dur", 0) / 1e6
        count[where] += 1
        by_name[where][e["name"]] += e.get("dur", 0) / 1e6
    return [
        {"process": p, "thread": t, "seconds": s, "events": count[(p, t)], "top": by_name[(p, t)].most_common(top)}
        for (p, t), s in seconds.most_common()
    ]


def traced(fn: Callable[[], Any], out: str, top: int = 10) -> tuple[float, list[dict]]:
    """(wall seconds of `fn()` until its result is ready, `summarise(..., top)` of its trace written to `out`)."""
    with jax.profiler.trace(out, create_perfetto_trace=True):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        wall = time.perf_counter() - start
    newest = max(glob.glob(os.path.join(out, "**", "perfetto_trace.json.gz"), recursive=True), key=os.path.getmtime)
    with gzip.open(newest) as f:
        trace = json.load(f)
    return wall, summarise(trace["traceEvents"] if isinstance(trace, dict) else trace, top)


def print_summary(rows: list[dict], streams: int) -> None:
    """Print the `streams` largest streams or threads of `summarise`'s rows with their largest operations."""
    for row in rows[:streams]:
        print(f"\n{row['process']} / {row['thread']}: {row['seconds']:.3f} s in {row['events']:,} events")
        for op, seconds in row["top"]:
            print(f"  {seconds:8.3f} s  {op[:100]}")
