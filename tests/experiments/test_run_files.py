"""The commands that read run folders and write results (`bidal_jax.run.runfiles`, `rundir.writing`) on damaged
folders and failing disks, without training: a damaged file is one `error:` line naming it and exit 2, a disk or
permission failure while writing one line and exit 4, a missing output folder is refused before the work, and a
failed write leaves no temporary file."""

import errno
import os
import types

import matplotlib.figure
import mujoco
import pytest

import envs_mjx
from bidal_jax.run import runfiles
from experiments import cli, evaluate, plot
from experiments.paper import claims, curves
from tests.conftest import TODAY, write_fake_run


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def damage(path, how: str) -> None:
    """Make the file `path` binary ("binary": bytes that are not UTF-8), end in 200 kB of NUL bytes ("nul"),
    or a folder ("folder")."""
    if how == "folder":
        os.remove(path)
        os.mkdir(path)
        return
    with open(path, "ab") as f:
        f.write(b"\xff\xfe\x81" * 64 if how == "binary" else b"\0" * 200_000)


@pytest.mark.parametrize("how, why", [("binary", "damaged: "), ("nul", "damaged: it holds NUL bytes"),
                                      ("folder", "is a directory, not a file")])
def test_plot_names_the_damaged_file_in_one_line_and_exits_2(tmp_path, capsys, how, why):
    run_dir = str(tmp_path / "run")
    write_fake_run(run_dir, "planar_reach", [[0.5]] * 2, None)
    damage(os.path.join(run_dir, "metrics.csv"), how)
    assert plot.main([run_dir, "--out", str(tmp_path / "curves")]) == cli.EXIT_BAD_INPUT
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith(f"error: {os.path.join(run_dir, 'metrics.csv')}: {why}")
    assert not (tmp_path / "curves.png").exists()


def test_plot_refuses_a_missing_out_folder_before_reading_and_maps_a_full_disk_to_exit_4(
    tmp_path, capsys, monkeypatch
):
    run_dir = str(tmp_path / "run")
    write_fake_run(run_dir, "planar_reach", [[0.5]] * 2, None)
    missing = tmp_path / "nope"
    assert plot.main([run_dir, "--out", str(missing / "curves")]) == cli.EXIT_BAD_INPUT
    assert error_lines(capsys.readouterr().err) == [
        f"error: --out: the folder {missing} does not exist; create it or name another"]

    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full)
    out = str(tmp_path / "curves")
    assert plot.main([run_dir, "--out", out]) == cli.EXIT_DISK
    assert error_lines(capsys.readouterr().err) == [
        f"error: no space left on device while writing {out}.png and {out}.csv; free some space or fix the "
        "permissions and run the command again"]


def test_curves_report_over_a_run_with_a_binary_metrics_csv_is_one_line_and_exit_2(tmp_path, no_nicol, capsys):
    out = tmp_path / "out"
    write_fake_run(str(out / "planar_reach" / "proprio_baseline"), "planar_reach", [[0.5, 0.5]] * 3, None,
                   agent="proprio_baseline")
    broken = out / "planar_reach" / "multimodal_bidal" / "metrics.csv"
    write_fake_run(str(broken.parent), "planar_reach", [[0.5, 0.5]] * 3, None)
    damage(broken, "binary")
    argv = ["--tasks", "planar_reach", "--agents", "proprio_baseline,multimodal_bidal", "--seeds", "2", "--epochs",
            "3", "--report", "--out", str(out)]
    assert curves.main(argv) == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    (line,) = error_lines(err)
    assert line.startswith(f"error: {broken}: damaged: not UTF-8 text (byte ") and "Traceback" not in err
    assert not (out / "table.md").exists()  # the table stops rather than take the run for one never trained


def test_claims_over_a_noise_run_ending_in_nul_bytes_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(envs_mjx, "make", lambda name, **kw: types.SimpleNamespace(physics_id=TODAY))
    for name in ("curves", "transfer"):
        (tmp_path / name).mkdir()
    broken = tmp_path / "noise" / "multimodal_bidal"
    write_fake_run(str(broken), "nicol_slide", [[0.5] * 15] * 3, None, physics=[TODAY])
    damage(broken / "metrics.csv", "nul")
    out = tmp_path / "claims.md"
    argv = ["--curves", str(tmp_path / "curves"), "--noise", str(tmp_path / "noise"), "--transfer",
            str(tmp_path / "transfer"), "--out", str(out)]
    assert claims.main(argv) == cli.EXIT_BAD_INPUT
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith(f"error: {broken / 'metrics.csv'}: damaged: it holds NUL bytes (the first at byte ")
    assert not out.exists()


def test_claims_refuse_a_missing_out_folder_first_and_a_full_disk_leaves_no_temporary_file(
    tmp_path, monkeypatch, capsys
):
    monkeypatch.setattr(envs_mjx, "make", lambda name, **kw: types.SimpleNamespace(physics_id=TODAY))
    folders = []
    for name in ("curves", "noise", "transfer"):
        (tmp_path / name).mkdir()
        folders += [f"--{name}", str(tmp_path / name)]
    assert claims.main([*folders, "--out", str(tmp_path / "nope" / "claims.md")]) == cli.EXIT_BAD_INPUT
    assert "--out: the folder" in capsys.readouterr().err
    real_open = open

    def full(path, mode="r", *args, **kwargs):  # the temporary file is created, then the disk is full
        f = real_open(path, mode, *args, **kwargs)
        if "w" in mode:
            f.write = lambda text: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device"))
        return f

    monkeypatch.setattr(runfiles, "open", full, raising=False)
    out = tmp_path / "claims.md"
    assert claims.main([*folders, "--out", str(out)]) == cli.EXIT_DISK
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith(f"error: no space left on device while writing {out};")
    assert sorted(os.listdir(tmp_path)) == ["curves", "noise", "transfer"]  # no claims.md, no claims.md.tmp


def test_evaluate_refuses_a_video_or_json_folder_that_does_not_exist_before_evaluating(tmp_path, capsys):
    for flag, name in (("--video", "out.mp4"), ("--json", "out.json")):
        path = tmp_path / "nope" / name
        assert evaluate.main(["--run-dir", str(tmp_path), flag, str(path)]) == cli.EXIT_BAD_INPUT
        assert error_lines(capsys.readouterr().err) == [
            f"error: {flag}: the folder {path.parent} does not exist; create it or name another"]


def test_evaluate_without_an_opengl_platform_is_refused_before_the_episodes(finished, tmp_path, monkeypatch, capsys):
    run_dir, _ = finished

    def no_gl(*args, **kwargs):
        raise mujoco.FatalError("an OpenGL platform library has not been loaded into this process")

    monkeypatch.setattr(mujoco, "Renderer", no_gl)
    monkeypatch.setattr(evaluate, "evaluate_seeds", lambda *a, **k: pytest.fail("evaluated before the check"))
    path = tmp_path / "out.mp4"
    assert evaluate.main(["--run-dir", run_dir, "--video", str(path), "--quiet"]) == cli.EXIT_BAD_INPUT
    (line,) = error_lines(capsys.readouterr().err)
    assert line.startswith(f"error: --video {path}: MuJoCo cannot render on this machine (an OpenGL platform")
    assert not path.exists()
