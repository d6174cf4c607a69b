"""The project's processes import mujoco.mjx without MuJoCo Warp (experiments.start_process) and give it Warp when an
env steps on it (envs_mjx.enable_warp): checked in a fresh interpreter, since this one may have imported warp
already."""

import subprocess
import sys
import textwrap

CHECK = textwrap.dedent("""
    import importlib.util, sys
    import experiments, envs_mjx
    assert "warp" not in sys.modules, "the process imported warp"
    import mujoco.mjx.warp as mjx_warp
    assert not mjx_warp.WARP_INSTALLED
    if importlib.util.find_spec("warp") is None:
        try:
            envs_mjx.enable_warp()
        except ImportError:
            print("absent")
    else:
        envs_mjx.enable_warp()
        from mujoco.mjx._src import io
        assert mjx_warp.WARP_INSTALLED and io.wp is sys.modules["warp"] and io.mjwp is mjx_warp.mujoco_warp
        assert mjx_warp.types.GraphMode is sys.modules["warp"].JaxCallableGraphMode
        print("enabled")
""")


def test_warp_is_imported_only_when_asked_for():
    result = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().splitlines()[-1] in ("absent", "enabled"), result.stdout
