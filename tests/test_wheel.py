"""The built wheel works outside the repository: it holds every module and model, and from a
fresh virtual environment, in a directory outside the repo, it builds every env and runs one
tiny training epoch (slow: builds a wheel and compiles; about a minute).

The wheel is built (`pip wheel --no-deps`) from a copy of exactly the folders pyproject.toml
packages, so that stale in-tree build output cannot leak into it. It is installed with
`--no-deps` into a fresh venv whose `.pth` file adds the site-packages of the interpreter running
the tests (`site.getsitepackages()`, processed as site directories), so that jax, mujoco and the
rest come from wherever this interpreter finds them: a venv's own, or the base's when it runs
outside one (`--system-site-packages` would give the base interpreter's, which inside a venv lack
them). That environment may also hold this project as an
editable install, whose import finder would serve the repository's sources; it comes after
the normal path search, which finds the wheel in the venv's own site-packages first, and
the venv's Python runs with `-I` (no PYTHONPATH, no user site, not started from the repo),
and the script asserts that every module it imports lies in the venv's site-packages.
"""

import fnmatch
import os
import shutil
import site
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).resolve().parent.parent

# run by the venv's Python, from a directory outside the repository
SCRIPT = """
import sysconfig
import jax, jax.numpy as jnp
import envs_mjx, envs_mjx.base, bidal_jax.train
from bidal_jax.config import Config, RunConfig, TrainConfig
from bidal_jax.run.devices import make_seeded
from bidal_jax.train import make_train

site = sysconfig.get_paths()["purelib"]
for where in (envs_mjx.__file__, str(envs_mjx.base.ASSETS_DIR), bidal_jax.train.__file__):
    assert where.startswith(site), f"{where} is not in the venv's site-packages {site}"

for name in envs_mjx.names():
    env = envs_mjx.make(name, render=False)  # loads the model from the wheel
    if name in ("planar_reach", "ur5_reach"):  # NICOL steps take 20-45 s to compile
        state = jax.jit(env.step)(jax.jit(env.reset)(jax.random.PRNGKey(0)), jnp.zeros(env.action_size))
        assert int(state.info["step"]) == 1, name

cfg = TrainConfig(num_envs=4, cycles_per_epoch=1, updates_per_cycle=1, batch_size=8, buffer_episodes=8, eval_envs=4)
init, epoch = make_seeded(*make_train(envs_mjx.make("planar_reach", render=False),
                                      Config(RunConfig(agent="proprio_baseline"), cfg)))
state, metrics = epoch(init(jax.random.split(jax.random.PRNGKey(0), 1)))
assert int(metrics["env_steps"][0]) > 0, metrics
print("wheel ok")
"""


def shipped_packages() -> dict[str, Path]:
    """Each package pyproject.toml ships -> its source folder (`packages` and `package-dir`)."""
    setup = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = setup.get("package-dir", {})
    return {pkg: ROOT / folders.get(pkg, pkg.replace(".", "/")) for pkg in setup["packages"]}


def expected_files() -> set[str]:
    """Paths in the wheel of every module under the shipped folders and of their package data."""
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"].get("package-data", {})
    expected = set()
    for pkg, folder in shipped_packages().items():
        prefix = pkg.replace(".", "/")
        for path in folder.rglob("*"):
            rel = path.relative_to(folder).as_posix()
            if path.suffix == ".py" or any(fnmatch.fnmatch(rel, p) for p in data.get(pkg, [])):
                expected.add(f"{prefix}/{rel}")
    return expected


def make_venv(venv: Path) -> Path:
    """A venv at `venv` that sees this interpreter's site-packages after its own; its Python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    purelib = subprocess.run([str(python), "-I", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    lines = [f"import site; site.addsitedir({path!r})" for path in site.getsitepackages()]
    (Path(purelib) / "outer_site_packages.pth").write_text("\n".join(lines) + "\n")
    return python


def build_wheel(tmp: Path) -> Path:
    """Build the wheel from a clean copy of pyproject.toml, README.md and the shipped folders."""
    src = tmp / "src"
    for name in ("pyproject.toml", "README.md"):
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / name, src / name)
    for folder in shipped_packages().values():
        shutil.copytree(folder, src / folder.relative_to(ROOT), dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp / "dist"), str(src)],
                   check=True)
    (wheel,) = (tmp / "dist").glob("*.whl")
    return wheel


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_repository(tmp_path):
    wheel = build_wheel(tmp_path)
    missing = expected_files() - set(zipfile.ZipFile(wheel).namelist())
    assert not missing, f"the wheel lacks {sorted(missing)}; list new packages in pyproject.toml"

    python = make_venv(tmp_path / "venv")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q",
                    str(wheel)], check=True)

    work = tmp_path / "elsewhere"
    work.mkdir()
    # share the suite's persistent compilation cache (tests/conftest.py), if it has one
    env = {**os.environ, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0.5"}
    if jax.config.jax_compilation_cache_dir:
        env["JAX_COMPILATION_CACHE_DIR"] = str(jax.config.jax_compilation_cache_dir)
    result = subprocess.run([str(python), "-I", "-c", SCRIPT], cwd=work, env=env, capture_output=True, text=True,
                            check=False)
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.strip().endswith("wheel ok")
