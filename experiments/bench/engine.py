"""MJX's two GPU physics engines side by side: its JAX implementation against MuJoCo Warp.

    python -m experiments.bench.engine --out engine.json            # everything below
    python -m experiments.bench.engine --parts step trajectories    # a subset

Parts (each guarded: one that fails is reported as its error and the others still run):
- `step`: env steps per second of the NICOL control step (all substeps) with random actions, at each
  `--num-envs`, physics alone (`render=False`) and with the 42×42 camera, per backend; the first call's
  seconds (trace, compile, first run; cold or warm depending on the caches) and the median of warm runs.
- `camera`: the project's ray caster (envs_mjx.camera) against MJX's Warp renderer (`create_render_context`,
  `refit_bvh`, `render`) on the same reset states, frames per second.
- `trajectories`: the same reset states and fixed action sequences (random, and the scripted controller's
  closed loop) on both backends; the largest difference of arm joints and cube position per step horizon,
  and the scripted controller's success on each.
- `epoch`: whole training epochs of nicol_slide multimodal_bidal (the preset) at `--seeds`, per backend:
  compile + first epoch and the median warm epoch.

Run it twice in a row to see cold and warm compilation (JAX's persistent cache is off here, so XLA
compiles each time; Warp caches its kernels in its own kernel cache).
"""

from __future__ import annotations

import argparse
import json
import time
import traceback

import jax
import numpy as np

from experiments.bench.programs import make_env, seeded_program, timed
from experiments.probes.grasping import grasp_policy

BACKENDS = ("jax", "warp")


def random_actions(key: jax.Array, steps: int, n: int, size: int) -> jax.Array:
    return jax.random.uniform(key, (steps, n, size), minval=-1.0, maxval=1.0)


def open_loop_program(env, n: int):
    """jit of: reset `n` envs, play actions [steps, n, A]; returns per-step qpos, cube position and image mean."""

    @jax.jit
    def run(key, actions):
        states = jax.vmap(env.reset)(jax.random.split(key, n))

        def body(state, action):
            state = jax.vmap(env.step)(state, action)
            return state, (state.data.qpos, state.obs["achieved_goal"], state.obs["image"].mean(axis=(1, 2, 3)))

        return jax.lax.scan(body, states, actions)[1]

    return run


def parse_options(text: str) -> dict:
    """`model` -> {} (the model's own settings); `iterations=5,cone=elliptic` -> physics options
    (`Env.set_options` converts and checks the values)."""
    if text == "model":
        return {}
    return {name: value for name, _, value in (item.partition("=") for item in text.split(","))}


def step_rates(name: str, num_envs: list[int], steps: int, repeats: int, backends=BACKENDS, renders=(False, True),
               options_list=("model",)) -> list[dict]:
    rows = []
    for options in options_list:
        for backend in backends:
            for render in renders:
                for n in num_envs:
                    env = make_env(name, backend, n, render, parse_options(options))
                    run = open_loop_program(env, n)
                    key = jax.random.PRNGKey(0)
                    actions = random_actions(jax.random.PRNGKey(1), steps, n, env.action_size)
                    t = timed(lambda: jax.block_until_ready(run(key, actions)), repeats)
                    rows.append({"options": options, "backend": backend, "render": render, "num_envs": n,
                                 "substeps": env.n_substeps, **t,
                                 "env_steps_per_second": n * steps / t["warm_seconds"]})
                    print(rows[-1], flush=True)
    return rows


def camera_rates(name: str, num_envs: list[int], repeats: int) -> list[dict]:
    from mujoco import mjx

    rows = []
    for n in num_envs:
        env = make_env(name, "warp", n, render=False)
        data = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), n)).data
        ours = jax.jit(jax.vmap(lambda d: env.camera.render(env.mjx_model, d)))
        t = timed(lambda: ours(data).block_until_ready(), repeats)
        rows.append({"renderer": "project ray caster", "num_envs": n, **t, "frames_per_second": n / t["warm_seconds"]})
        print(rows[-1], flush=True)
        context = mjx.create_render_context(
            env.mj_model, nworld=n, cam_res=(42, 42), render_rgb=True, render_depth=False, use_textures=False,
            use_shadows=False, enabled_geom_groups=[0, 1, 2], cam_active=[env.camera_name])
        handle = context.pytree()

        @jax.jit
        def warp_render(d):
            d = mjx.refit_bvh(env.mjx_model, d, handle)
            return mjx.render(env.mjx_model, d, handle)[0]

        t = timed(lambda: jax.block_until_ready(warp_render(data)), repeats)
        rows.append({"renderer": "MJX Warp render", "num_envs": n, **t, "frames_per_second": n / t["warm_seconds"]})
        print(rows[-1], flush=True)
    return rows


def scripted_program(env, n: int, steps: int):
    spec = env.observation_spec

    @jax.jit
    def run(key):
        states = jax.vmap(env.reset)(jax.random.split(key, n))

        def body(state, _):
            action = jax.vmap(lambda o: grasp_policy(o, spec))(state.obs)
            state = jax.vmap(env.step)(state, action)
            return state, (state.data.qpos, state.obs["achieved_goal"])

        final, trace = jax.lax.scan(body, states, None, length=steps)
        return trace, final.metrics["success"]

    return run


def trajectories(name: str, n: int) -> dict:
    """Largest differences between the backends after 1, 10 and 50 steps, arm joints (rad) and cube (m)."""
    out = {}
    envs = {b: make_env(name, b, n, render=False) for b in BACKENDS}
    steps = envs["jax"].episode_length
    actions = random_actions(jax.random.PRNGKey(1), steps, n, envs["jax"].action_size)
    key = jax.random.PRNGKey(0)
    traces = {b: open_loop_program(e, n)(key, actions) for b, e in envs.items()}
    scripted = {b: scripted_program(e, n, steps)(key) for b, e in envs.items()}
    for label, pair in (("random_actions", {b: t[:2] for b, t in traces.items()}),
                        ("scripted", {b: s[0] for b, s in scripted.items()})):
        (qj, gj), (qw, gw) = (np.asarray(pair["jax"][0]), np.asarray(pair["jax"][1])), \
            (np.asarray(pair["warp"][0]), np.asarray(pair["warp"][1]))
        out[label] = {f"after_{h}": {"arm_joints_rad": float(np.abs(qj[:h, :, :6] - qw[:h, :, :6]).max()),
                                     "cube_m": float(np.linalg.norm(gj[:h] - gw[:h], axis=-1).max()),
                                     "cube_median_m": float(np.median(np.linalg.norm(gj[h - 1] - gw[h - 1], axis=-1)))}
                      for h in (1, 10, steps)}
    out["scripted_success"] = {b: float(np.asarray(s[1]).mean()) for b, s in scripted.items()}
    print(out, flush=True)
    return out


def epochs(name: str, agent: str, seeds_list: list[int], repeats: int) -> list[dict]:
    rows = []
    for backend in BACKENDS:
        for seeds in seeds_list:
            start = time.perf_counter()
            init, epoch, config, env, *_ = seeded_program(name, agent, seeds, backend=backend)
            holder = {"state": init(jax.random.split(jax.random.PRNGKey(0), seeds))}

            def one_epoch():
                holder["state"], metrics = epoch(holder["state"])
                jax.block_until_ready(metrics)

            build = time.perf_counter() - start
            t = timed(one_epoch, repeats)
            first, sec = build + t["first_call_seconds"], t["warm_seconds"]
            steps = seeds * config.cycles_per_epoch * config.num_envs * env.episode_length
            rows.append({"backend": backend, "agent": agent, "seeds": seeds, "build_compile_first_epoch_seconds": first,
                         "epoch_seconds": sec, "env_steps_per_second": steps / sec})
            print(rows[-1], flush=True)
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="nicol_slide")
    parser.add_argument("--agent", default="multimodal_bidal")
    parser.add_argument("--parts", nargs="+", default=["step", "camera", "trajectories", "epoch"],
                        choices=["step", "camera", "trajectories", "epoch"])
    parser.add_argument("--num-envs", type=int, nargs="+", default=[512, 4096])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 5])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS, help="`step` part")
    parser.add_argument("--renders", nargs="+", default=["physics", "camera"], choices=["physics", "camera"],
                        help="`step` part: physics alone, with the camera")
    parser.add_argument("--options", nargs="+", default=["model"],
                        help="`step` part: physics options to compare, each `model` (the model's own) or "
                             "NAME=VALUE,... (envs_mjx.base.Env.set_options), e.g. iterations=5,ls_iterations=8")
    parser.add_argument("--out", default=None, help="JSON file for the results")
    args = parser.parse_args(argv)
    results = {"device": str(jax.devices()[0]), "jax": jax.__version__}
    jobs = {"step": lambda: step_rates(args.env, args.num_envs, args.steps, args.repeats, args.backends,
                                       [r == "camera" for r in args.renders], args.options),
            "camera": lambda: camera_rates(args.env, args.num_envs, args.repeats),
            "trajectories": lambda: trajectories(args.env, 256),
            "epoch": lambda: epochs(args.env, args.agent, args.seeds, args.repeats)}
    for part in args.parts:
        try:
            results[part] = jobs[part]()
        except Exception as error:  # noqa: BLE001 - a measurement that fails is a result too
            traceback.print_exc()
            results[part] = {"error": f"{type(error).__name__}: {error}"[:2000]}
        if args.out:
            with open(args.out, "w") as f:
                json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
