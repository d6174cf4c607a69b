"""What results/ may hold (.gitignore): run folders (config.json, metrics.csv), plots and tables; of an unfinished
run also its latest checkpoint without the replay buffer (`python -m experiments.carry`), from which a later
process on any machine continues it, and so of a finished transfer source until its transfer arm has started
(`experiments.carry.keeps_checkpoint`); never another finished run's checkpoints, a second checkpoint or a buffer."""

import os

from experiments import report
from experiments.carry import folder_bytes, keeps_checkpoint
from tests.conftest import write_fake_run
from tests.helpers import REPO

# a carried checkpoint of a 5-seed NICOL image run is 7-9 MB; a checkpoint must stay small enough to commit
MAX_CHECKPOINT_BYTES = 16 * 2**20


def misplaced_checkpoints(root: str) -> list[str]:
    """One line per checkpoint under `root` that results/ must not hold."""
    problems = []
    for run_dir, folders, _ in sorted(os.walk(root)):
        if "checkpoints" not in folders:
            continue
        steps = sorted(os.listdir(os.path.join(run_dir, "checkpoints")))
        run = report.load_run(run_dir)  # RunError (a failure naming the folder) where it is not a run with epochs
        epochs, reached = run["config"]["run"]["epochs"], int(run["epoch"][-1])
        if not keeps_checkpoint(run_dir):
            problems.append(f"{run_dir}: finished ({reached} of {epochs} epochs) but keeps checkpoints")
        if steps != [str(reached)]:
            problems.append(f"{run_dir}: checkpoints {steps}; keep the latest alone, that of epoch {reached}")
        for step in steps:
            path = os.path.join(run_dir, "checkpoints", step)
            if os.path.exists(os.path.join(path, "buffer")):
                problems.append(f"{run_dir}: checkpoint {step} holds its replay buffer")
            if folder_bytes(path) > MAX_CHECKPOINT_BYTES:
                problems.append(f"{run_dir}: checkpoint {step} is over {MAX_CHECKPOINT_BYTES // 2**20} MiB")
    return problems


def test_results_hold_only_the_carried_checkpoints_of_unfinished_runs():
    assert misplaced_checkpoints(os.path.join(REPO, "results")) == []


def test_misplaced_checkpoints_are_found(tmp_path):
    def write(name, epochs_run, checkpoint_epoch, buffer=False):
        run_dir = str(tmp_path / name)
        write_fake_run(run_dir, "planar_reach", [(0.1,)] * epochs_run, checkpoint_epoch, given={"epochs": 3},
                       buffer=buffer)
        return run_dir

    write("finished-kept", 3, None)
    write("carried", 2, 2)
    assert misplaced_checkpoints(str(tmp_path)) == []
    finished, buffered, older = write("finished", 3, 3), write("buffered", 2, 2, buffer=True), write("older", 2, 1)
    os.makedirs(os.path.join(buffered, "checkpoints", "1"))
    assert misplaced_checkpoints(str(tmp_path)) == [
        f"{buffered}: checkpoints ['1', '2']; keep the latest alone, that of epoch 2",
        f"{buffered}: checkpoint 2 holds its replay buffer",
        f"{finished}: finished (3 of 3 epochs) but keeps checkpoints",
        f"{older}: checkpoints ['1']; keep the latest alone, that of epoch 2",
    ]


def test_a_finished_transfer_source_keeps_its_checkpoint_until_the_transfer_arm_starts(tmp_path):
    out = tmp_path / "transfer"
    source = str(out / "source")
    write_fake_run(source, "nicol_slide", [(0.5,)] * 3, 3, given={"epochs": 3}, buffer=False)
    assert misplaced_checkpoints(str(tmp_path)) == []  # no transfer arm yet: the source's parameters are needed
    write_fake_run(str(out / "transfer"), "nicol_lift_reduced", [(0.1,)], 1, given={"epochs": 3}, buffer=False)
    assert misplaced_checkpoints(str(tmp_path)) == [f"{source}: finished (3 of 3 epochs) but keeps checkpoints"]
    scratch = str(out / "scratch")  # any other finished run keeps none, whatever its neighbours
    write_fake_run(scratch, "nicol_lift_reduced", [(0.1,)] * 3, 3, given={"epochs": 3}, buffer=False)
    assert f"{scratch}: finished (3 of 3 epochs) but keeps checkpoints" in misplaced_checkpoints(str(tmp_path))
