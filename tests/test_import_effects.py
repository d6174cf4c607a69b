"""The libraries change nothing on import (docs/design.md, convention 12): importing every module of `envs_mjx` and
`bidal_jax` in a fresh process leaves `os.environ`, `sys.stdout` and `sys.stderr` as they were and prints nothing;
the process settings are the command lines' (`experiments.start_process`)."""

import json
import os
import subprocess
import sys

import experiments

MARK = "-- the libraries' imports start here --"
# JAX (TF_CPP_MIN_LOG_LEVEL, TPU_SKIP_MDS_QUERY), MuJoCo MJX (a line about an absent Warp) and Gymnasium
# (PYGAME_HIDE_SUPPORT_PROMPT) have effects of their own on import; they are imported first, so that what follows
# the mark is the libraries' alone
PROBE = f"""
import importlib, json, os, pkgutil, sys
import gymnasium, jax, mujoco.mjx
print({MARK!r}, flush=True)
print({MARK!r}, file=sys.stderr, flush=True)
environ, streams = dict(os.environ), (sys.stdout, sys.stderr)
import bidal_jax, envs_mjx
modules = [m.name for package in (bidal_jax, envs_mjx)
           for m in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
for name in modules:
    importlib.import_module(name)
changed = sorted(k for k in set(environ) | set(os.environ) if environ.get(k) != os.environ.get(k))
same = streams[0] is sys.stdout and streams[1] is sys.stderr
sys.stdout.flush()
with open(sys.argv[1], "w") as f:
    json.dump({{"modules": modules, "changed": changed, "same_streams": same}}, f)
"""


def test_importing_the_libraries_changes_no_environment_variable_stream_or_output(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MUJOCO_GL", "PYOPENGL_PLATFORM")}
    report = tmp_path / "report.json"
    done = subprocess.run([sys.executable, "-c", PROBE, str(report)], env=env, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    found = json.loads(report.read_text())
    assert {"bidal_jax.train", "bidal_jax.run.loop", "envs_mjx.nicol", "envs_mjx.gym"} <= set(found["modules"])
    assert found["changed"] == []
    assert found["same_streams"]
    assert done.stdout.split(MARK, 1)[1].strip() == ""
    assert done.stderr.split(MARK, 1)[1].strip() == ""


def test_the_command_lines_set_the_measured_flags_where_the_callers_environment_does_not():
    every, cpu_only = experiments.XLA_FLAGS_BY_JAXLIB["0.10"]
    assert experiments.xla_flags("0.10.2", gpu_plugin=False) == every + cpu_only
    assert experiments.xla_flags("0.10.1", gpu_plugin=True) == every
    assert experiments.xla_flags("9.1.0", gpu_plugin=False) == ()  # a release not measured: none (XLA aborts on
    # a flag it does not know)
    given = "--xla_backend_optimization_level=2 --xla_force_host_platform_device_count=4"
    assert experiments.with_flags(given, cpu_only) == given
    assert experiments.with_flags("", every) == " ".join(every)
