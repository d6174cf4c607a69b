"""Each part of a gradient update against its own floor: the parts, the chips' peaks and the table that sets a
part's measured GPU time beside the larger of its floors (`experiments.bench.roofline` counts the floors;
`experiments.paper.results_docs` renders the table from results/scaling/roofline/)."""

from __future__ import annotations

import collections
from typing import NamedTuple


class Chip(NamedTuple):
    """A GPU's dense peaks (FLOP/s) by a dot's dtype, and its memory bandwidth (bytes/s)."""

    peaks: dict
    bandwidth: float


# NVIDIA's data sheets (SXM parts): dense tensor-core rates, HBM bandwidth
CHIPS = {"H100": Chip({"bf16": 989.4e12, "f32": 494.7e12}, 3.35e12),
         "H200": Chip({"bf16": 989.4e12, "f32": 494.7e12}, 4.8e12)}
MODELS = "forward and inverse models"
# the parts of an update, in the order the tables list them; a network's forward and backward passes are one part
# except the encoder's, whose two passes are most of an image update
PARTS = ("encoder forward", "encoder backward", "critic", "actor", MODELS, "optimiser (Adam)",
         "target networks (Polyak)", "replay and HER sampling", "losses and the rest")


def part_of(component: str) -> str:
    """`tracing.component`'s label, at any depth, -> a part of `PARTS` ("update: Critic backward" and "update:
    Critic/Dense_0 backward" -> "critic"); a label of no network is kept."""
    name = component.removeprefix("update: ")
    path, _, direction = name.rpartition(" ")
    network = path.split("/")[0]
    if network == "Encoder":
        return f"encoder {direction}"
    return {"Critic": "critic", "Actor": "actor", "ForwardModel": MODELS, "InverseModel": MODELS}.get(network, name)


def chip_of(device_kind: str) -> tuple[str, Chip]:
    """The `CHIPS` entry a device kind names ("NVIDIA H100 80GB HBM3" -> H100); ValueError for any other."""
    for label, chip in CHIPS.items():
        if label in device_kind.upper():
            return label, chip
    raise ValueError(f"device {device_kind!r}: no peaks known; one of {', '.join(CHIPS)} is allowed")


def floor_seconds(part: dict, chip: Chip) -> tuple[float, float]:
    """(compute floor, memory floor) of a `floors` part on `chip`, in seconds."""
    compute = sum(n / chip.peaks[dtype] for dtype, n in part["flops"].items())
    return compute, part["bytes"] / chip.bandwidth


def parts_table(counted: dict, measured: dict) -> tuple[list[str], list[list[str]]]:
    """(head, rows): each part's FLOPs, bytes, floors on the measured device's chip, its GPU time per update
    (`measured`: a row of `experiments.bench.updates --json`, its parts grouped by `part_of`; a part it names that
    `PARTS` lacks gets a row with no floor) and that time over the larger floor; then the update's wall time
    against its floor, the larger of all parts' compute and memory."""
    label, chip = chip_of(measured["device_kind"])
    took = collections.Counter()
    for row in measured["parts"]:
        took[part_of(row["component"])] += row["ms"]
    rows, totals = [], [0.0, 0.0]
    for part in counted["parts"] + [{"part": p, "flops": {}, "bytes": 0} for p in took if p not in PARTS]:
        compute, memory = floor_seconds(part, chip)
        totals = [totals[0] + compute, totals[1] + memory]
        floor, ms = max(compute, memory), took.get(part["part"])
        flops, moved = sum(part["flops"].values()), part["bytes"]
        rows.append([part["part"], f"{flops / 1e9:.2f}" if flops else "—", f"{moved / 1e6:.2f}" if moved else "—",
                     f"{1e6 * compute:.1f}", f"{1e6 * memory:.1f}", "—" if ms is None else f"{1e3 * ms:.0f}",
                     "—" if ms is None or floor == 0 else f"{ms / 1e3 / floor:.0f}×"])
    floor = max(totals)
    rows.append(["the update (wall time)", "", "", f"{1e6 * totals[0]:.1f}", f"{1e6 * totals[1]:.1f}",
                 f"{1e3 * measured['ms']:.0f}", f"{measured['ms'] / 1e3 / floor:.0f}×"])
    head = ["part", "GFLOP", "MB", f"compute floor (µs, {label})", f"memory floor (µs, {label})", "measured (µs)",
            "× its floor"]
    return head, rows
