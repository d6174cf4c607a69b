"""The learner: multimodal BidAL (DDPG + HER + UVFA with forward and inverse models) in JAX.

Two layers. The modules of this package are the algorithm: pure JAX functions over pytrees
(networks, losses, replay, normalizer, noise, acting, train, config); they never touch the
file system, Orbax, `jax.distributed` or command-line validation. `bidal_jax.run` is the run
machinery above them: checks, run directories, metrics, checkpoints, devices, processes and
transfer. Imports run downwards only (docs/design.md).
"""
