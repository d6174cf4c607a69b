"""Benchmarks: env and training throughput (`throughput`), time to a success threshold (`success`),
the Gymnasium adapter's cost (`gym_adapter`) and a profile of one training epoch (`epoch_profile`)."""
