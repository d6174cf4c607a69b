"""The vision branch alone against its floor: forward and backward passes of an update's frames, per conv_impl.

    python -m experiments.bench.encoder                      # patch, banded, toeplitz (and pallas on a GPU); bfloat16
    python -m experiments.bench.encoder --impls toeplitz pallas --seeds 5 --frames 4096 --dtype bfloat16
    python -m experiments.bench.encoder --impls pallas --pallas-blocks 32 64 128 --pallas-warps 4 8   # its tiling

Times, for `--seeds` vmapped seeds, the vision branch (`bidal_jax.networks.VisionBranch`: the four 3×3 convs with
ELU and the dense layer) of `--frames` frames per seed, forward and backward (the gradients of its weights and
biases: frames are data, so the first layer's input gradient is not asked for), in one jitted call: an update's
encoder work. Each figure is the median of `--repeats` warm calls. Beside it, the floor of that work on an H100
(989 TFLOP/s bf16 dense, 3.35 TB/s): the branch's useful FLOPs (forward 2·k²·C·F per output of each conv and
2·in·out for the dense layer; backward as much again for the weight gradients and once more for the input gradients
of every layer but the first) and the bytes a fused kernel cannot avoid (each uint8 frame read once, the bf16
features written and their gradient read), and the measured time over the larger of the two.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools

import jax
import jax.numpy as jnp
import numpy as np

from bidal_jax import encoder_kernel
from bidal_jax.config import CONV_IMPLS, NetworkConfig
from bidal_jax.conv_matrices import same_pads
from bidal_jax.networks import FUSED_IMPL, VisionBranch, parse_strides
from experiments.bench.programs import timed

PEAK_FLOPS, PEAK_BYTES = 989e12, 3.35e12  # one H100 SXM: bf16 dense tensor-core FLOP/s, HBM3 bytes/s
FRAME = (42, 42, 1)


def branch_flops(strides: tuple[int, ...], channels: int, features: int, k: int = 3) -> tuple[float, float]:
    """Useful FLOPs of one frame through the vision branch (four convs, then the dense layer): (forward, backward);
    backward = weight gradients of every layer + input gradients of all but the first."""
    size, c_in, forward = FRAME[0], FRAME[2], []
    for layer, stride in enumerate(strides):
        pads = (0, 0, 0, 0) if layer == 0 else same_pads(size, size, k, stride)
        size = (size + pads[0] + pads[1] - k) // stride + 1
        forward.append(2.0 * k * k * c_in * channels * size * size)
        c_in = channels
    forward.append(2.0 * size * size * channels * features)
    return sum(forward), sum(forward) + sum(forward[1:])


def floor_seconds(frames: int, strides: tuple[int, ...], channels: int, features: int) -> dict[str, float]:
    """The floor of forward + backward of `frames` frames: compute, memory and their larger."""
    forward, backward = branch_flops(strides, channels, features)
    flops = frames * (forward + backward)
    bytes_ = frames * (np.prod(FRAME) + 2 * 2 * features)
    return {"gflop": flops / 1e9, "mb": bytes_ / 1e6, "compute_s": flops / PEAK_FLOPS, "memory_s": bytes_ / PEAK_BYTES,
            "floor_s": max(flops / PEAK_FLOPS, bytes_ / PEAK_BYTES)}


def encoder_step(impl: str, dtype: str, seeds: int, frames: int):
    """A jitted forward + backward of the vision branch over `frames` frames of each of `seeds` seeds, and its
    inputs (random weights and frames)."""
    net = NetworkConfig(conv_impl=impl, vision_dtype=dtype)
    branch = VisionBranch(net.conv_channels, net.vision_features, parse_strides(net.conv_strides), impl=impl,
                          dtype=jnp.dtype(dtype))
    keys = jax.random.split(jax.random.PRNGKey(0), seeds)
    images = jax.random.randint(jax.random.PRNGKey(1), (seeds, frames, *FRAME), 0, 256).astype(jnp.uint8)
    params = jax.vmap(lambda key: branch.init(key, images[0, :1]))(keys)

    def loss(p, x):
        return jnp.sum(branch.apply(p, x))

    step = jax.jit(jax.vmap(jax.grad(loss)))
    return step, params, images


@contextlib.contextmanager
def pallas_tiling(block: int, num_warps: int):
    """The fused kernel traced inside with `block` frames and `num_warps` warps a program (its module settings,
    restored after)."""
    saved = encoder_kernel.BLOCK, encoder_kernel.NUM_WARPS
    encoder_kernel.BLOCK, encoder_kernel.NUM_WARPS = block, num_warps
    try:
        yield
    finally:
        encoder_kernel.BLOCK, encoder_kernel.NUM_WARPS = saved


def runs(impls: list[str], blocks: list[int], warps: list[int]):
    """(row label, the context to build and time it in) of each implementation, the fused one once per tiling."""
    for impl in impls:
        if impl != FUSED_IMPL:
            yield impl, impl, contextlib.nullcontext()
            continue
        for block, num_warps in itertools.product(blocks, warps):
            yield impl, f"{impl} ({block} frames, {num_warps} warps)", pallas_tiling(block, num_warps)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--impls", nargs="+", choices=CONV_IMPLS,
                        default=[impl for impl in CONV_IMPLS if impl != FUSED_IMPL or jax.default_backend() == "gpu"])
    parser.add_argument("--dtype", default="bfloat16", choices=("float32", "bfloat16"))
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--frames", type=int, default=4096,
                        help="frames per seed through forward and backward (a batch of 2,048: obs and next obs)")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--pallas-blocks", nargs="+", type=int, default=[encoder_kernel.BLOCK],
                        help="frames per program of the fused kernel on a GPU (powers of two >= 16)")
    parser.add_argument("--pallas-warps", nargs="+", type=int, default=[encoder_kernel.NUM_WARPS],
                        help="warps per program of the fused kernel (powers of two)")
    args = parser.parse_args(argv)
    if any(b < 16 or b & (b - 1) for b in args.pallas_blocks) or any(w < 1 or w & (w - 1) for w in args.pallas_warps):
        parser.error("--pallas-blocks: powers of two >= 16; --pallas-warps: powers of two")
    net = NetworkConfig()
    floor = floor_seconds(args.seeds * args.frames, parse_strides(net.conv_strides), net.conv_channels,
                          net.vision_features)
    print(f"device: {jax.devices()[0].device_kind}; {args.seeds} seeds × {args.frames} frames, {args.dtype}")
    print(f"floor (H100): {floor['gflop']:.1f} GFLOP → {floor['compute_s'] * 1e6:.1f} µs; {floor['mb']:.1f} MB → "
          f"{floor['memory_s'] * 1e6:.1f} µs; floor {floor['floor_s'] * 1e6:.1f} µs")
    print("| conv_impl | compile s | ms per call | × floor |")
    print("| --- | --- | --- | --- |")
    for impl, label, tiling in runs(args.impls, args.pallas_blocks, args.pallas_warps):
        try:
            with tiling:
                step, params, images = encoder_step(impl, args.dtype, args.seeds, args.frames)
                times = timed(lambda: jax.block_until_ready(step(params, images)), args.repeats)
        except Exception as err:  # a tiling the compiler refuses (registers, shared memory): the sweep goes on
            print(f"| {label} | failed: {type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''} |")
            continue
        print(f"| {label} | {times['first_call_seconds']:.1f} | {times['warm_seconds'] * 1e3:.3f} | "
              f"{times['warm_seconds'] / floor['floor_s']:.0f} |")


if __name__ == "__main__":
    main()
