"""Camera benchmark: frames per second of the ray-cast camera with culling (each moving geom cast against its
window of rays, `envs_mjx.camera`) and without (every geom against every ray), on the same scenes, and how often a
batch fell back to casting every ray.

    python -m experiments.bench.camera                                 # planar_reach and nicol_slide, 64 envs
    python -m experiments.bench.camera --envs ur5_reach nicol_lift --num-envs 16 256

The scenes are those of a random-action rollout from `env.reset` (one batch of `--num-envs` per step of
`--steps`), so the arm is seen in many poses. Each figure is the median of `--repeats` timed renders of all those
batches after a warm-up (compilation excluded); it prints a Markdown table.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

import envs_mjx
from bidal_jax import acting
from experiments.bench.programs import timed


def scenes(env, num_envs: int, steps: int) -> jax.Array:
    """The mjx.Data of `steps` batches of `num_envs` envs along a random-action rollout, stacked [steps, num_envs]."""
    return acting.rollout(env, acting.random_policy(env.action_size), jax.random.PRNGKey(0), num_envs,
                          steps=steps, record=lambda step: step.next_state.data)[1]


def camera_figures(name: str, num_envs: int, steps: int, repeats: int) -> dict[str, float]:
    """Frames per second with and without culling, and the share of batches that fell back to every ray."""
    env = envs_mjx.make(name, render=False)
    cam = env.camera
    data = jax.jit(lambda: scenes(env, num_envs, steps))()
    figures = {}
    for label, cull in (("all rays", False), ("culled", True)):
        frames = jax.vmap(lambda one, cull=cull: cam.geom_map(env.mjx_model, one, cull))
        render = jax.jit(lambda d, frames=frames: jax.lax.map(frames, d))
        seconds = timed(lambda: render(data).block_until_ready(), repeats)["warm_seconds"]
        figures[f"{label} frames/s"] = steps * num_envs / seconds
    fits = jax.jit(jax.vmap(jax.vmap(lambda one: cam.fits_windows(env.mjx_model, one))))(data)
    figures["batches cast in full"] = float(jnp.mean(~jnp.all(fits, axis=1)))
    return figures


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", default=["planar_reach", "nicol_slide"], choices=envs_mjx.names())
    parser.add_argument("--num-envs", nargs="+", type=int, default=[64])
    parser.add_argument("--steps", type=int, default=20, help="rollout steps whose scenes are rendered")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per figure (median)")
    args = parser.parse_args(argv)
    print(f"device: {jax.devices()[0].device_kind}")
    print("| env | envs | all rays frames/s | culled frames/s | speed-up | batches cast in full |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name in args.envs:
        for num_envs in args.num_envs:
            f = camera_figures(name, num_envs, args.steps, args.repeats)
            print(f"| {name} | {num_envs} | {f['all rays frames/s']:,.0f} | {f['culled frames/s']:,.0f} | "
                  f"{f['culled frames/s'] / f['all rays frames/s']:.2f}× | {f['batches cast in full']:.0%} |")


if __name__ == "__main__":
    main()
