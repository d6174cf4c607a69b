"""The import structure (docs/design.md): the algorithm stays below the run machinery, nothing imports
upwards, no command-line script imports another. Read from the sources' syntax trees: nothing is run."""

import ast
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("bidal_jax", "envs_mjx", "experiments")
# what the algorithm never imports: checkpoints, processes, the file system, the run machinery, envs
ALGORITHM_NEVER = ("orbax", "jax.distributed", "jax.experimental.multihost_utils", "os", "pathlib", "shutil", "io",
                   "tensorboardX", "tqdm", "mujoco", "bidal_jax.run", "envs_mjx", "experiments")
# package -> the packages it may import (data flows one way: experiments -> envs_mjx, bidal_jax)
MAY_IMPORT = {"bidal_jax": {"bidal_jax"}, "envs_mjx": {"envs_mjx"}, "experiments": set(PACKAGES)}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {module_name(p): p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))}


def imports(path: Path) -> list[tuple[str, bool]]:
    """(module imported, whether the import stands inside a function) for each import of the file; a
    `from package import name` of a module of this tree counts as that module."""
    found = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                found.extend((alias.name, in_function) for alias in child.names)
            elif isinstance(child, ast.ImportFrom) and child.module and not child.level:
                for alias in child.names:
                    full = f"{child.module}.{alias.name}"
                    found.append((full if full in MODULES else child.module, in_function))
            visit(child, nested)

    visit(ast.parse(path.read_text()), False)
    return found


def project(name: str) -> bool:
    return name.partition(".")[0] in PACKAGES


def algorithm_modules() -> list[str]:
    return [m for m in MODULES if m.startswith("bidal_jax") and not m.startswith("bidal_jax.run")]


@pytest.mark.parametrize("module", algorithm_modules())
def test_the_algorithm_imports_no_disk_process_checkpoint_or_run_machinery(module):
    for name, _ in imports(MODULES[module]):
        bad = [never for never in ALGORITHM_NEVER if name == never or name.startswith(never + ".")]
        assert not bad, f"{module} imports {name}"
    calls = [n.func.id for n in ast.walk(ast.parse(MODULES[module].read_text()))
             if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    assert "open" not in calls, f"{module} opens a file"


@pytest.mark.parametrize("module", list(MODULES))
def test_no_deferred_import_hides_an_edge_and_packages_import_one_way(module):
    package = module.partition(".")[0]
    for name, in_function in imports(MODULES[module]):
        if project(name):
            assert not in_function, f"{module} imports {name} inside a function"
            assert name.partition(".")[0] in MAY_IMPORT[package], f"{module} imports {name}"


def test_the_module_graph_has_no_cycle():
    graph = {m: {n for n, _ in imports(p) if n in MODULES and n != m} for m, p in MODULES.items()}
    state: dict[str, str] = {}

    def visit(m, trail):
        state[m] = "open"
        for n in graph[m]:
            assert state.get(n) != "open", " -> ".join([*trail, m, n])
            if n not in state:
                visit(n, [*trail, m])
        state[m] = "done"

    for m in graph:
        if m not in state:
            visit(m, [])


def commands() -> set[str]:
    """The experiments modules that are command lines (they run as `python -m ...`)."""
    return {m for m, p in MODULES.items() if m.startswith("experiments") and '__name__ == "__main__"' in p.read_text()}


def test_no_command_line_script_imports_another():
    for module in (m for m in MODULES if m.startswith("experiments")):
        scripts = [n for n, _ in imports(MODULES[module]) if n in commands() and n != module]
        assert not scripts, f"{module} imports the command line {scripts[0]}"


def test_experiments_is_grouped_and_shares_no_module_name_with_the_learner():
    top = [p for p in (ROOT / "experiments").iterdir() if p.suffix == ".py"]
    assert len(top) <= 8, sorted(p.name for p in top)
    learner = {p.stem for p in (ROOT / "bidal_jax").rglob("*.py")} - {"__init__"}
    clashes = [m for m, p in MODULES.items() if m.startswith("experiments") and p.stem in learner]
    assert not clashes, clashes


def test_every_module_reads_its_docstring_first():
    missing = [m for m, p in MODULES.items() if os.path.getsize(p) and not ast.get_docstring(ast.parse(p.read_text()))]
    assert not missing, missing
