"""The run machinery: everything around the algorithm that touches disk, devices, processes or signals.

`validate` and `preflight` check a run before anything is compiled or written (`rundir` locks its
directory and guards its disk), `loop` runs its
epochs (with `metrics` and the `guard`), `devices` lays seeds and env shards out over devices,
`checkpoint` and `policy` save and load with Orbax, `multihost` joins several processes, and
`transfer` starts a run from another run's parameters. These modules import the algorithm
(`bidal_jax.*`); no module of the algorithm imports them.
"""
