"""Benchmarks: env and training throughput (`throughput`), time to a success threshold (`success`),
the Gymnasium adapter's cost (`gym_adapter`), a profile of one training epoch (`epoch_profile`), MJX's
JAX physics against MuJoCo Warp (`engine`), compile time (`compile_time`) and learning speed of preset
variants (`sweep`); `programs` builds the training program they share."""
