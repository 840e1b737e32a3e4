"""Whole training runs as a user starts them: kill -9 and resume, refusals, two processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from mcdenoise.cli.main import main
from mcdenoise.train.runlog import read_metrics
from train_tiny_data import make_tiny_dataset

PY = sys.executable
#: Small, fast and exercising both KPCN phases (branches for 80 % of the steps, then the image).
RUN = ["--model", "kpcn", "--crop", "16", "--batch", "2", "--workers", "0", "--val-every", "0", "--no-progress",
       "--checkpoint-every", "2", "--sampling", "uniform"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "data")


def _cmd(data: Path, out: Path, steps: int, *extra: str) -> list[str]:
    return [PY, "-m", "mcdenoise.cli.main", "train", *RUN, "--data", str(data), "--out", str(out), "--steps", str(steps), *extra]


def _env() -> dict[str, str]:
    # Same thread count in every process, or float reductions could be ordered differently.
    return dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(Path(__file__).parent))


#: Runs the train CLI, stopping itself (SIGSTOP) once the metrics row of step 5 is written: the
#: test then kills it at a known point whatever the CPU's speed (a polling window missed on fast
#: or loaded machines, issue 18). Step 5 is past the step-4 checkpoint, so the resume must also
#: drop a metrics row that no checkpoint covers.
_STOP_AT_5 = """
import os, signal, sys
from mcdenoise.train import runlog
write = runlog.MetricsLog.write
def stopping_write(self, row):
    write(self, row)
    if row["step"] == 5:
        os.kill(os.getpid(), signal.SIGSTOP)
runlog.MetricsLog.write = stopping_write
from mcdenoise.cli.main import main
sys.exit(main(sys.argv[1:]))
"""


def _wait_stopped(proc: subprocess.Popen, timeout: float) -> bool:
    """True once ``proc`` is stopped by a signal (state T in /proc), False if it exits or times out."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        with open(f"/proc/{proc.pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] in ("T", "t"):
                return True
        time.sleep(0.02)
    return False


def _losses(run: Path) -> list[str]:
    return [r["loss"] for r in read_metrics(run / "metrics.csv")]


def test_kill_and_resume_is_bit_exact(tiny: Path, tmp_path: Path) -> None:
    """Catches any state a resume fails to restore (Adam moments, RNG, schedule position, data
    position, phase) or metrics.csv rows duplicated or lost across a SIGKILL: the resumed run's
    per-step losses and final weights must equal an uninterrupted run's bit for bit (the
    uninterrupted one runs in-process, so this also checks the CLI adds nothing process-specific)."""
    steps = 12
    ref = tmp_path / "ref"
    # The uninterrupted run in this process (one subprocess fewer), with the subprocesses' thread count.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(_cmd(tiny, ref, steps)[3:]) == 0
    finally:
        torch.set_num_threads(threads)

    run = tmp_path / "killed"
    argv = _cmd(tiny, run, steps)
    proc = subprocess.Popen([PY, "-c", _STOP_AT_5, *argv[3:]], env=_env(), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    stopped = _wait_stopped(proc, 600)  # a bound for a hung process only: the stop is an event
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert stopped, f"the run never reached step 5 (exit {proc.returncode})"
    done_before = len(_losses(run))
    assert done_before == 5, "the kill must land mid-run, after step 5"
    ckpts = sorted((run / "checkpoints").glob("step_*"))
    assert ckpts and int(ckpts[-1].name[5:]) < steps

    res = subprocess.run(_cmd(tiny, run, steps, "--resume"), env=_env(), capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert _losses(run) == _losses(ref) and len(_losses(ref)) == steps
    phases = [r["phase"] for r in read_metrics(run / "metrics.csv")]
    assert phases.count("branches") == round(0.8 * steps) and phases[-1] == "image"
    a, b = load_file(str(ref / "model.safetensors")), load_file(str(run / "model.safetensors"))
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _one_line_error(capsys: pytest.CaptureFixture, argv: list[str], *needles: str) -> None:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    for n in needles:
        assert n in err, err


def test_run_folder_refusals(tiny: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """Catches a new run overwriting an existing one, a resume with other settings, --force
    deleting a folder that is not a run, and a finished run left without its final weights."""
    out = tmp_path / "run"
    base = ["train", *RUN, "--data", str(tiny), "--out", str(out), "--steps", "1"]
    assert main(base) == 0
    capsys.readouterr()
    weights = (out / "model.safetensors").read_bytes()
    _one_line_error(capsys, base, "already exists", "--resume", "--force")
    _one_line_error(capsys, base + ["--resume", "--lr", "0.1"], "does not match", "lr")
    assert (out / "model.safetensors").read_bytes() == weights
    assert main(base + ["--resume"]) == 0  # finished: nothing to do, nothing changed
    assert (out / "model.safetensors").read_bytes() == weights
    before = load_file(str(out / "model.safetensors"))
    (out / "model.safetensors").unlink()  # as if killed after the last checkpoint, before the final write
    assert main(base + ["--resume"]) == 0
    after = load_file(str(out / "model.safetensors"))  # (header bytes may differ: metadata order)
    assert before.keys() == after.keys() and all(torch.equal(before[k], after[k]) for k in before)
    weights = (out / "model.safetensors").read_bytes()
    assert main(["train", "--out", str(out), "--resume"]) == 0  # settings from config.json
    capsys.readouterr()
    other = tmp_path / "notarun"
    other.mkdir()
    (other / "precious.txt").write_text("keep")
    _one_line_error(capsys, ["train", *RUN, "--data", str(tiny), "--out", str(other), "--force"], "not a run folder")
    assert (other / "precious.txt").exists()
    assert main(base + ["--force", "--steps", "2"]) == 0
    assert len(_losses(out)) == 2
    capsys.readouterr()
    _one_line_error(capsys, ["train", "--model", "kpcn", "--data", str(tmp_path), "--out", str(tmp_path / "x")], "manifest.json")
    _one_line_error(capsys, ["train", "--model", "nope", "--data", str(tiny), "--out", str(tmp_path / "y")], "unknown model")
    _one_line_error(capsys, ["train", *RUN, "--data", str(tiny), "--out", str(tmp_path / "z"), "--crop", "99"], "smaller than")
    assert not (tmp_path / "z").exists()  # refused before the run folder was made
    if not torch.cuda.is_available():
        _one_line_error(capsys, ["train", *RUN, "--data", str(tiny), "--out", str(tmp_path / "z"), "--device", "cuda"], "CUDA")


# In the default run (about 11 s on 2 idle cores): CI must see that torchrun training still works.
def test_two_processes_train_like_one_with_the_whole_batch(tiny: Path, tmp_path: Path) -> None:
    """Catches ranks reading overlapping rows, gradients summed instead of averaged, ranks
    drifting apart, or a rank other than 0 writing the run folder: torchrun with 2 gloo processes
    and batch 4 (2 rows each) must give the weights of 1 process with batch 4."""
    steps = 4
    one, two = tmp_path / "one", tmp_path / "two"
    args = ["train", *RUN, "--batch", "4", "--data", str(tiny), "--steps", str(steps)]
    subprocess.run([PY, "-m", "mcdenoise.cli.main", *args, "--out", str(one)], check=True, env=_env(),
                   capture_output=True, timeout=300)
    res = subprocess.run([PY, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", "-m",
                          "mcdenoise.cli.main", *args, "--out", str(two)], env=_env(), capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    la, lb = [float(x) for x in _losses(one)], [float(x) for x in _losses(two)]
    assert len(la) == len(lb) == steps
    assert la == pytest.approx(lb, rel=1e-5)
    a, b = load_file(str(one / "model.safetensors")), load_file(str(two / "model.safetensors"))
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=1e-4, atol=1e-6)
    assert (two / "config.json").is_file() and '"world_size": 2' in (two / "config.json").read_text()
