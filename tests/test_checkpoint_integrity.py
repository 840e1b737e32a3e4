"""Damaged checkpoints are found and passed over on --resume (issue 22 item 2); one writer per
run folder (item 8).

A resume verifies each checkpoint's ``checksums.json`` (and, for folders written before checksums,
that the files load) and falls back to the newest intact checkpoint with one line saying so; it
never resumes from a flipped weight, nor prints a traceback for a truncated or garbage file.
"""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import pytest
import torch

from mcdenoise.cli.main import main
from mcdenoise.train.checkpoint import CHECKSUM_FILE, Checkpoint, CheckpointError, list_checkpoints, load_checkpoint, \
    save_checkpoint
from mcdenoise.train.runlog import read_metrics
from mcdenoise.models import build_model
from train_tiny_data import make_tiny_dataset

RUN = ["--model", "wskp", "--crop", "16", "--batch", "2", "--workers", "0", "--val-every", "0", "--no-progress",
       "--checkpoint-every", "2", "--keep-every", "2", "--sampling", "uniform", "--threads", "1"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(data, an uninterrupted 8-step run with checkpoints at 2, 4, 6 and 8)."""
    root = tmp_path_factory.mktemp("ck")
    data = make_tiny_dataset(root / "data")
    assert main(["train", *RUN, "--data", str(data), "--out", str(root / "ref"), "--steps", "8"]) == 0
    return data, root / "ref"


def _killed_after_6(ref: Path, run: Path) -> Path:
    """A copy of ``ref`` as if killed after the step-6 checkpoint."""
    shutil.copytree(ref, run)
    shutil.rmtree(run / "checkpoints" / "step_00000008")
    (run / "model.safetensors").unlink()
    (run / "result.json").unlink()
    return run


def _losses(run: Path) -> list[str]:
    return [r["loss"] for r in read_metrics(run / "metrics.csv")]


def _flip_top_byte_of_a_float(path: Path) -> None:
    """XOR 0x40 into the exponent byte of the first float32 of the first tensor (as the issue did)."""
    raw = bytearray(path.read_bytes())
    header = struct.unpack("<Q", raw[:8])[0]
    raw[8 + header + 3] ^= 0x40
    path.write_bytes(bytes(raw))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _garbage(path: Path) -> None:
    path.write_bytes(b"\x80\x04garbage" * 7)


def _legacy_garbage_state(ck: Path) -> None:
    """A folder from before checksums (no checksums.json) whose state.pt is garbage."""
    (ck / CHECKSUM_FILE).unlink()
    _garbage(ck / "state.pt")


@pytest.mark.parametrize("damage,name", [
    (_flip_top_byte_of_a_float, "model.safetensors"),
    (_truncate, "model.safetensors"),
    (_garbage, "model.safetensors"),
    (_truncate, "state.pt"),
    (_garbage, "state.pt"),
    (_legacy_garbage_state, ""),
])
def test_resume_falls_back_to_newest_intact_checkpoint(runs, tmp_path, capfd, damage, name) -> None:
    """Catches issue 22 item 2: a flipped weight in the newest checkpoint resumed silently (rc 0, one
    weight at -1e37, a diverging run), and truncated/garbage state.pt or weights gave tracebacks. The
    resume must name the damage in one line, continue from step 4 and match an uninterrupted run."""
    data, ref = runs
    run = _killed_after_6(ref, tmp_path / "run")
    damage(run / "checkpoints" / "step_00000006" / name)
    capfd.readouterr()
    rc = main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8", "--resume"])
    err = capfd.readouterr().err
    assert rc == 0, err
    lines = [ln for ln in err.splitlines() if "damaged" in ln]
    assert len(lines) == 1 and "step_00000006" in lines[0] and "step 4" in lines[0], err
    assert "Traceback" not in err
    assert _losses(run) == _losses(ref)


def test_every_checkpoint_damaged_is_one_line(runs, tmp_path, capfd) -> None:
    """Catches a traceback (or a silent restart from step 0) when no checkpoint is intact."""
    data, ref = runs
    run = _killed_after_6(ref, tmp_path / "run")
    for ck in list_checkpoints(run):
        _truncate(ck.path / "state.pt")
    capfd.readouterr()
    assert main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8", "--resume"]) == 1
    text = capfd.readouterr().err
    err = [ln for ln in text.splitlines() if "error" in ln]
    assert len(err) == 1 and "Traceback" not in text, text
    assert "every checkpoint is damaged" in err[0] and "--force" in err[0], err


def test_checkpoint_byte_flip_sweep(tmp_path) -> None:
    """Catches any byte of a checkpoint (weights, state, checksums.json) whose change goes unnoticed:
    every single-byte flip either raises CheckpointError or loads exactly the saved weights and state."""
    torch.manual_seed(0)
    model = build_model("wskp", "small")
    state = {"optimizer": {"state": {}, "param_groups": []}, "rng_cpu": torch.get_rng_state(), "skipped": 0}
    ck = save_checkpoint(tmp_path, 2, model, state)
    want = {k: v.clone() for k, v in model.state_dict().items()}
    for name in ("model.safetensors", "state.pt", CHECKSUM_FILE):
        path = ck.path / name
        good = path.read_bytes()
        step = max(1, len(good) // 400)  # about 400 positions per file, both ends included
        for i in sorted(set(range(0, len(good), step)) | set(range(max(0, len(good) - 64), len(good)))):
            bad = bytearray(good)
            bad[i] ^= 0x40
            path.write_bytes(bytes(bad))
            other = build_model("wskp", "small")
            try:
                got = load_checkpoint(Checkpoint(ck.path, 2), other)
            except CheckpointError:
                continue
            finally:
                path.write_bytes(good)
            assert all(torch.equal(other.state_dict()[k], v) for k, v in want.items()), (name, i)
            assert torch.equal(got["rng_cpu"], state["rng_cpu"]), (name, i)


def test_one_writer_per_run_folder(runs, tmp_path, capfd) -> None:
    """Catches issue 22 item 8: concurrent `--resume` x3 or `--force` mid-run both ran, and one died
    late with an AssertionError traceback or a rename error. While a live process holds the run's
    lock, both are refused in one line and the folder is left as it was; a dead holder's lock is
    taken over, and a finished run leaves no lock behind."""
    import os
    import subprocess

    from mcdenoise.io import safety
    from mcdenoise.train.loop import run_lock_path

    data, ref = runs
    run = _killed_after_6(ref, tmp_path / "run")
    before = sorted(p.name for p in run.rglob("*"))
    lock = run_lock_path(run)
    with safety.WriterLock(lock, "another train"):  # this (live) process plays the running trainer
        for extra in (["--resume"], ["--force"]):
            capfd.readouterr()
            assert main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8", *extra]) == 1
            text = capfd.readouterr().err
            err = [ln for ln in text.splitlines() if "error" in ln]
            assert len(err) == 1 and "another mcdenoise run is writing here" in err[0], text
            assert sorted(p.name for p in run.rglob("*")) == before
    dead = subprocess.Popen(["true"])
    dead.wait()
    lock.write_text(__import__("json").dumps({"pid": dead.pid, "host": safety._HOST, "what": "killed"}))
    assert main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8", "--resume"]) == 0
    assert not lock.exists() and os.path.isfile(run / "model.safetensors")


@pytest.mark.parametrize("fail", ["torch_save", "safetensors"])
def test_disk_full_during_a_checkpoint_is_one_line(runs, tmp_path, capfd, monkeypatch, fail) -> None:
    """Catches issue 22 item 9's checkpoint case: a full disk while writing a checkpoint ended in a
    traceback (torch.save's RuntimeError); it must be one line naming the checkpoint, leave no
    temporary folder, and the run must resume from the previous checkpoint."""
    import errno

    import mcdenoise.train.checkpoint as ckmod

    data, ref = runs
    run = tmp_path / "run"
    real_save, real_file = ckmod.torch.save, ckmod.save_file
    calls = {"n": 0}

    def full_disk(*a, **k):
        calls["n"] += 1
        if calls["n"] >= 3:  # the third checkpoint (step 6) finds the disk full
            if fail == "torch_save":
                raise RuntimeError("[enforce fail at inline_container.cc:778] . PytorchStreamWriter failed "
                                   "writing file data/3: file write failed")
            raise OSError(errno.ENOSPC, "No space left on device")
        return (real_save if fail == "torch_save" else real_file)(*a, **k)

    if fail == "torch_save":
        monkeypatch.setattr(ckmod.torch, "save", full_disk)
    else:
        monkeypatch.setattr(ckmod, "save_file", full_disk)
    capfd.readouterr()
    assert main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8"]) == 1
    text = capfd.readouterr().err
    err = [ln for ln in text.splitlines() if "error" in ln]
    assert len(err) == 1 and "Traceback" not in text, text
    assert "step_00000006" in err[0] and ("disk is full" in err[0] or "disk full" in err[0]), err
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step_00000002", "step_00000004"]
    monkeypatch.undo()
    assert main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8", "--resume"]) == 0
    assert _losses(run) == _losses(ref)


def test_killed_plot_temporary_is_removed(runs, tmp_path) -> None:
    """Catches issue 22 item 10: a `.loss.tmp-*.png` of a killed run survived every later resume."""
    import subprocess

    from mcdenoise.io import safety

    data, ref = runs
    run = _killed_after_6(ref, tmp_path / "run")
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = run / f".loss.tmp-{safety._HOST}-{dead.pid}-0123abcd.png"
    stale.write_bytes(b"half a PNG")
    assert main(["train", *RUN, "--data", str(data), "--out", str(run), "--steps", "8", "--resume"]) == 0
    assert not stale.exists()
