"""Each part of a gradient update against its own floor: what the chip could not do faster.

    python -m experiments.bench.roofline --env nicol_lift --agent multimodal_bidal --seeds 5 \\
        --out results/scaling/roofline/nicol_lift-multimodal_bidal.json

A part's floor is the larger of two lower bounds on its time in one update of all seeds:

- compute: the useful FLOPs of its matmuls at the chip's dense peak for their dtype (bfloat16 at the tensor cores'
  bfloat16 rate; float32 at their TF32 rate, which XLA's default precision lets a float32 dot use). The update is
  lowered, not compiled, for one seed, with every conv written as one matmul over its k×k patches (`conv_impl`
  patch), so no dot multiplies a zero that a banded or Toeplitz form would add; each dot of XLA's unoptimised HLO
  counts 2·(output elements)·(contracted size) for the part its op name names (`tracing.component`), times the
  seeds. Elementwise work (ELUs, Adam's arithmetic) is not counted: the memory bound covers it.
- memory: the bytes the part cannot avoid moving through HBM, at the chip's bandwidth. The encoder's forward pass
  reads each frame it encodes once (uint8); each network's passes read its parameters once and write their
  gradients once; Adam reads the parameters, their gradients and two moments and writes three of them (7 words a
  parameter); Polyak reads both parameter sets and writes the targets (3 words); replay sampling reads the batch's
  vector fields once (its frames are the encoder's read). Activations are not counted: a fused kernel keeps a
  frame's in on-chip memory (a frame's largest map, 14×14×16, is 6 KB of bfloat16).

The measured side is `python -m experiments.bench.updates --profile DIR --json FILE` on a GPU: each part's device
time per update. `floor_table.parts_table` sets the two side by side, a part against its own floor (what
`experiments.paper.results_docs` renders from results/scaling/roofline/).
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import re
from typing import Iterator, NamedTuple

import jax

import envs_mjx
from bidal_jax.config import AGENTS, ConfigError
from bidal_jax.run import validate
from bidal_jax.train import Shards, make_learner, make_train
from experiments.bench import tracing
from experiments.bench.floor_table import MODELS, PARTS, part_of, parts_table
from experiments.bench.programs import full_buffer, parse_variant, program_config
from experiments.report import markdown_table

WORD = 4  # bytes of a float32 parameter, gradient or moment

# each parameter group of `TrainState.params` and the parts whose passes read it or write its gradients
PARAM_PARTS = {"encoder": ("encoder forward", "encoder backward"), "critic": ("critic",), "actor": ("actor",),
               "forward": (MODELS,), "inverse": (MODELS,)}
_DEFINE = re.compile(r"^\s*(?:ROOT\s+)?%([\w.\-]+)\s*=\s*(\w+)\[([\d,]*)\]")
_DOT = re.compile(r"^\s*(?:ROOT\s+)?%[\w.\-]+\s*=\s*(\w+)\[([\d,]*)\]\S*\s+dot\(%([\w.\-]+), %[\w.\-]+\),"
                  r"\s*lhs_contracting_dims=\{([\d,]*)\}.*?op_name=\"([^\"]*)\"")


class Dot(NamedTuple):
    """A dot of an HLO module: its part of the update, its operands' dtype, its FLOPs, its output dims, op name."""

    part: str
    dtype: str
    flops: int
    out: tuple
    op_name: str


def _dims(text: str) -> tuple[int, ...]:
    return tuple(int(d) for d in text.split(",") if d)


def dots(hlo_text: str) -> Iterator[Dot]:
    """Every dot of an HLO module's text with its op name's part (`part_of`), its lhs operand's dtype and its FLOPs
    (2 · output elements · contracted elements)."""
    shapes = {m.group(1): (m.group(2), _dims(m.group(3))) for m in map(_DEFINE.match, hlo_text.splitlines()) if m}
    for m in map(_DOT.match, hlo_text.splitlines()):
        if m:
            _, out, lhs, contracting, op_name = m.groups()
            dtype, lhs_dims = shapes[lhs]
            k = math.prod(lhs_dims[int(i)] for i in contracting.split(",") if i)
            yield Dot(part_of(tracing.component(op_name)), dtype, 2 * math.prod(_dims(out)) * k, _dims(out), op_name)


def update_hlo(name: str, agent: str, variant: str = "preset") -> tuple[str, object, object, object]:
    """(XLA's unoptimised HLO text of one update of one seed, with op names; the abstract state; the config; the env)
    of `agent`'s preset on env `name` with `variant`'s overrides and every conv as a patch matmul."""
    train, network, _ = parse_variant(variant)
    config = program_config(name, agent, train, {**network, "conv_impl": "patch"})
    env = envs_mjx.make(name, render=config.agent.uses_image)
    init, _ = make_train(env, config)
    update = make_learner(env, config, Shards(1)).update
    key = jax.random.PRNGKey(0)
    state = jax.eval_shape(lambda k: full_buffer(init(k)), key)
    text = jax.jit(update).lower(state, key).compiler_ir("hlo").as_hlo_module().to_string()
    return text, state, config, env


def frames_encoded(found: list[Dot]) -> int:
    """Frames an update encodes: the rows of the encoder's first conv, over its passes (0 without a vision
    branch)."""
    return sum(d.out[0] for d in found if d.part == "encoder forward" and "PatchConv_0/" in d.op_name)


def floors(name: str, agent: str, seeds: int, variant: str = "preset") -> dict:
    """Per part of one update of `seeds` seeds: FLOPs by dtype and the bytes it cannot avoid (module docstring),
    with what they were counted from."""
    text, state, config, env = update_hlo(name, agent, variant)
    found = list(dots(text))
    if found and all(d.part == "losses and the rest" for d in found):
        raise ValueError("the update's op names carry no network scopes: count it in a process that has not "
                         "lowered a run's programs (`loop.short_source_locations`)")
    flops: dict[str, collections.Counter] = {part: collections.Counter() for part in PARTS}
    for d in found:
        flops.setdefault(d.part, collections.Counter())[d.dtype] += seeds * d.flops
    count = {group: sum(math.prod(leaf.shape) for leaf in jax.tree.leaves(tree))
             for group, tree in state.params.items()}
    moved = collections.Counter()
    for group, n in count.items():
        for part in PARAM_PARTS.get(group, ()):
            moved[part] += WORD * n  # its parameters read by its forward pass, or its gradients written
    frames = frames_encoded(found)
    moved["encoder forward"] += frames * math.prod(env.observation_spec.image_shape)
    moved["optimiser (Adam)"] += 7 * WORD * sum(count.values())
    moved["target networks (Polyak)"] += 3 * WORD * sum(math.prod(leaf.shape)
                                                      for leaf in jax.tree.leaves(state.target_params))
    spec, batch = env.observation_spec, config.train.batch_size
    moved["replay and HER sampling"] += WORD * batch * (2 * spec.proprio_size + 3 * spec.goal_size + env.action_size)
    return {"env": name, "agent": agent, "seeds": seeds, "variant": variant, "batch_size": batch,
            "frames_per_seed": frames, "parameters_per_seed": count,
            "parts": [{"part": part, "flops": dict(flops[part]), "bytes": seeds * moved[part]} for part in flops]}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench.roofline", description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="nicol_lift", choices=envs_mjx.names())
    parser.add_argument("--agent", default="multimodal_bidal", choices=list(AGENTS))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--variant", default="preset", help="k=v,net.k=v overrides of the preset "
                        "(as experiments.bench.sweep's); conv_impl is always patch")
    parser.add_argument("--measured", default="", help="`experiments.bench.updates --json`'s file: each of its rows "
                        "(variants) set beside the floors")
    parser.add_argument("--out", default="", help="write the counted floors here (JSON)")
    args = parser.parse_args(argv)
    try:
        validate.check_field("seeds", args.seeds)
        counted = floors(args.env, args.agent, args.seeds, args.variant)
    except ConfigError as err:
        raise SystemExit(f"error: {err}") from err
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump(counted, f, indent=1)
    print(f"{args.env} {args.agent} ({args.variant}), {args.seeds} seed(s), batch {counted['batch_size']}: "
          f"{counted['frames_per_seed']} frames a seed an update")
    for part in counted["parts"]:
        flops = ", ".join(f"{n / 1e9:.3f} {dtype}" for dtype, n in part["flops"].items()) or "0"
        print(f"  {part['part']}: GFLOP {flops}; {part['bytes'] / 1e6:.2f} MB")
    if args.measured:
        with open(args.measured, encoding="utf-8") as f:
            measured = json.load(f)
        for row in measured:
            head, rows = parts_table(counted, row)
            print(f"\n## {row['variant']} on {row['device_kind']}\n\n{markdown_table(head, rows)}")


if __name__ == "__main__":
    main()
