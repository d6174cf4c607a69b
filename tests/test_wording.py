"""The repository speaks of the product (docs/design.md, convention 9): no tracked text file names how the work
was organised or hosted, nor a hosting path. Every tracked text file is read, run configs and notes under results/
included (this file too: it keeps the words base64-encoded, so it does not say them either), except the metrics
tables and figures there (numbers and images).
And the code says what and why: no GPU model or wall-clock figure in the sources of the packages and commands (the
benches aside, whose output is timings): not in a comment, a docstring or a string; the figures are results/' data and
docs/results.md's, which is written from them."""

import base64
import os
import re
import subprocess

import pytest

from tests.helpers import REPO


def decoded(text: str) -> str:
    """A base64 text as the string it encodes: how this file holds the words it forbids."""
    return base64.b64decode(text).decode("utf-8")


# the words of the work's organisation and hosting, and the paths of the machines it ran on (decoded: a regular
# expression of whole words, some with a plural, and three path fragments)
FORBIDDEN = re.compile(decoded(
    "XGJzZXNzaW9ucz9cYnxcYmxlYXNlcz9cYnxcYmxlYXNlZFxifGRldmljZSB0aW1lfFxibGVudFxifFxibGVuZGluZ1xifFxic2l0dGluZ3M/XGJ8"
    "cm91bmQgb2Ygd29ya3wvd29yay98XC5kZXYvfC9yb290Lw=="), re.IGNORECASE)
# the one product use of a forbidden word: pytest's fixture scope (decoded: scope= and that scope's name, quoted)
ALLOWED = re.compile(decoded("c2NvcGU9WyInXXNlc3Npb25bIidd"))
# lines the pattern must find (decoded: seven lines, each with one of the words or paths)
FORBIDDEN_EXAMPLES = decoded(
    "dGhlIG5leHQgU2Vzc2lvbgpvbmUgbGVhc2Ugb2YgZm91ciBHUFVzCmEgbWFjaGluZSBsZW50IGZvcgppbiBhIGxhdGVyIHNpdHRpbmcKY2Qg"
    "L3dvcmsvbWFpbgpiYXNoIC5kZXYvbGF1bmNoLnNoCiJydW5fZGlyIjogIi9yb290L3Jlcy9jdXJ2ZXMi").splitlines()
# pytest's fixture decorator with that scope (decoded), which the allowed use spares
SCOPED_FIXTURE = decoded("QHB5dGVzdC5maXh0dXJlKHNjb3BlPSJzZXNzaW9uIik=")
DATA = re.compile(r"^results/.*\.(csv|png|svg)$")
# a GPU model or a wall-clock figure: the figures of a machine, which results/ holds with their commands: a number
# with a unit of time ("about 150 s", "2.4 ms", "20 minutes", "1.8 h"), time per epoch, a speed-up ("3× faster")
GPU_OR_TIMING = re.compile(
    r"[ABHV]100|[BH]200|s an epoch|(?<![\w.])\d(?:[\d,.]*\d)? ?(?:ms|µs|s|sec|seconds?|min|minutes?|h|hours?)\b"
    r"|\d ?(?:×|x|times) (?:faster|slower|as long|shorter|longer)\b")
# times in the code that are no measurement, spared: a duration's format, quoted ("300 s (5.0 min)"), and the control
# period (0.04 s of simulated time); by file, the parameters that a file states in words (its timeouts)
NOT_MEASURED = re.compile(r'"\d[\d,.]* (?:s|min|h)(?: \([\d.]+ (?:min|h)\))?"|\b0\.04 s\b')
PARAMETERS = {os.path.join("experiments", "cluster.py"): re.compile(r"\b30 s\b|\b0 seconds\b")}
CODE = ("bidal_jax", "envs_mjx", "experiments")
BENCHES = os.path.join("experiments", "bench")


def tracked_text_files() -> list[str]:
    """The tracked files that are text (UTF-8 without NUL bytes), less results/ data."""
    try:
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no tracked files to read")
    paths = [p for p in listed.decode().split("\0") if p and not DATA.match(p)]
    texts = []
    for path in paths:
        if not os.path.isfile(os.path.join(REPO, path)):
            continue
        with open(os.path.join(REPO, path), "rb") as f:
            data = f.read()
        try:
            if b"\0" not in data:
                data.decode("utf-8")
                texts.append(path)
        except UnicodeDecodeError:
            pass
    return texts


def hits(path: str) -> list[str]:
    """`path:line: text` for each line of the file with a forbidden word outside the allowed uses."""
    with open(os.path.join(REPO, path), encoding="utf-8") as f:
        lines = f.read().splitlines()
    return [f"{path}:{n}: {line.strip()[:120]}" for n, line in enumerate(lines, 1)
            if FORBIDDEN.search(ALLOWED.sub("", line))]


def test_the_pattern_finds_the_words_and_spares_the_product_uses():
    assert len(FORBIDDEN_EXAMPLES) == 7 and all(FORBIDDEN.search(s) for s in FORBIDDEN_EXAMPLES)
    assert FORBIDDEN.search(SCOPED_FIXTURE)
    assert not any(FORBIDDEN.search(ALLOWED.sub("", s)) for s in (
        SCOPED_FIXTURE, "rundir.release(run_dir)", "excellent", "silently", "round(x)"))


def test_no_tracked_text_file_speaks_of_how_the_work_was_organised():
    files = tracked_text_files()
    assert "README.md" in files and "docs/results.md" in files
    found = [hit for path in files for hit in hits(path)]
    assert found == [], "words of the work's organisation or hosting:\n" + "\n".join(found)


def code_files() -> list[str]:
    """The Python sources of `CODE`, relative to the repository, less the benches'."""
    found = []
    for top in CODE:
        for folder, dirs, files in os.walk(os.path.join(REPO, top)):
            dirs[:] = [d for d in dirs if d != "__pycache__"]
            found += [os.path.relpath(os.path.join(folder, f), REPO) for f in files if f.endswith(".py")]
    return sorted(path for path in found if not path.startswith(BENCHES + os.sep))


def timings(path: str, line: str) -> bool:
    """Whether the line of the file at `path` states a GPU model or a wall-clock figure, its spared times aside."""
    spared = NOT_MEASURED.sub("", line)
    return bool(GPU_OR_TIMING.search(PARAMETERS[path].sub("", spared) if path in PARAMETERS else spared))


def test_the_gpu_and_timing_pattern_finds_the_figures_and_spares_the_product():
    code = os.path.join("bidal_jax", "config.py")
    assert all(timings(code, s) for s in (
        "on one H100", "one H200 each", "an A100", "takes 2.4 ms", "5.6ms per update", "6.4 s an epoch",
        "1,600 updates an epoch", "from a cold start in about 150 s",
        "kernel cache, about 105 s that a grid pays", "within 20 minutes", "3 seconds", "1.5 min", "a 2 h job",
        "12 hours", "3× faster", "10 times as long", "about 1.5 s of every start"))
    assert not any(timings(code, s) for s in (
        "a control period of 0.04 s", "1,600 updates per epoch", "100 epochs", "items", "1 × cpu", "params",
        "3 seeds", "5 steps", "float32s", "0.05 m per step", "1.25 m/s", "(limit - compile_s) // per_seed",
        "min(1, max(2, 3))", 'else "42 s", "12.5 min" or "2.4 h"', '"8,720 s (2.4 h)"', "2 hosts", "r2s"))
    cluster = os.path.join("experiments", "cluster.py")
    assert not timings(cluster, "refused within 30 s") and timings(code, "refused within 30 s")


def test_no_gpu_model_or_timing_in_the_code():
    files = code_files()
    assert os.path.join("bidal_jax", "networks.py") in files and os.path.join("envs_mjx", "base.py") in files
    assert not any(path.startswith(BENCHES) for path in files)
    found = []
    for path in files:
        with open(os.path.join(REPO, path), encoding="utf-8") as f:
            found += [f"{path}:{n}: {line.strip()[:120]}" for n, line in enumerate(f, 1) if timings(path, line)]
    assert found == [], "GPU models or timings in the code (docs/results.md holds them):\n" + "\n".join(found)
