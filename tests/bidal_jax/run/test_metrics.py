"""A run's metrics (`bidal_jax/run/metrics.py`): TensorBoard's writer comes without PyTorch, which tensorboardX
would import where it is installed, and torch stays importable afterwards."""

import os
import subprocess
import sys
import textwrap


def test_tensorboard_is_imported_without_torch_and_torch_stays_importable(tmp_path):
    fake = tmp_path / "site" / "torch"
    fake.mkdir(parents=True)
    marker = tmp_path / "torch-imported"
    (fake / "__init__.py").write_text(f"open({str(marker)!r}, 'w').close()\nTensor = object\n")
    script = textwrap.dedent(f"""
        import os, sys
        from bidal_jax.run import metrics
        metrics.MetricsLog({str(tmp_path / 'run')!r}).write({{"epoch": 1, "success": 0.5}})
        assert "torch" not in sys.modules and not os.path.exists({str(marker)!r})
        import torch
        assert os.path.exists({str(marker)!r})
    """)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(fake.parent), os.environ.get("PYTHONPATH", "")]))
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert os.listdir(tmp_path / "run" / "tb")  # TensorBoard wrote its events
