"""Hand-written run directories for the report and plot tests."""

import csv
import json

import numpy as np

# per epoch: per-seed eval success, env_steps_total (summed over seeds), wall_time
RUN_A = [((0.2, 0.4), 16000, 10.0), ((0.4, 0.6), 32000, 20.0), ((0.8, 1.0), 48000, 30.0)]  # 2 seeds
RUN_B = [((0.0, 0.5, 1.0), 24000, 5.0), ((1.0, 1.0, 0.7), 48000, 9.0)]  # 3 seeds


def write_run(path, agent, rows, env="ur5_reach", lam=0.1):
    """A run directory as experiments/run.py writes it (the columns plot.py reads, and one more)."""
    seeds = len(rows[0][0])
    path.mkdir()
    config = {"run": {"env": env, "agent": agent, "seeds": seeds}, "train": {"intrinsic_lambda": lam}, "network": {}}
    (path / "config.json").write_text(json.dumps(config))
    with open(path / "metrics.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["epoch", "critic_loss", "eval_success", *[f"eval_success_seed{i}" for i in range(seeds)],
                         "env_steps_total", "wall_time"])
        for epoch, (success, steps, wall) in enumerate(rows, start=1):
            writer.writerow([epoch, 0.1, np.mean(success), *success, steps, wall])
    return str(path)
