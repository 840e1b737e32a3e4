"""The layout of a run folder of ``mcdenoise train``, and reading it (standard library only).

A run folder holds::

    config.json                          the run's configuration (train and model fields)
    model.safetensors                    final weights (absent until the run finishes)
    result.json                          the run's summary (wall time, device, steps)
    checkpoints/step_NNNNNNNN/           one folder per checkpoint: model.safetensors, state.pt
                                         and checksums.json (size + SHA-256 of both, written last)

Writing checkpoints and loading them into a model is :mod:`mcdenoise.train.checkpoint`'s job; this
module only names the files and finds intact checkpoints, so that loading weights
(:mod:`mcdenoise.models.weights`) needs neither torch's training code nor the training loop.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path

from mcdenoise.errors import FormatError

__all__ = ["CONFIG_FILE", "WEIGHTS_FILE", "RESULT_FILE", "CHECKPOINT_DIR", "CHECKSUM_FILE", "CHECKPOINT_FILES",
           "Checkpoint", "CheckpointError", "checkpoint_folder_name", "checkpoint_run", "sha256_file",
           "list_checkpoints", "latest_checkpoint", "verify_checkpoint", "intact_checkpoint"]

CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
RESULT_FILE = "result.json"
CHECKPOINT_DIR = "checkpoints"
CHECKSUM_FILE = "checksums.json"
#: Files of a complete checkpoint folder (weights, training state).
CHECKPOINT_FILES = (WEIGHTS_FILE, "state.pt")
_NAME = re.compile(r"^step_(\d{8})$")


class CheckpointError(FormatError):
    """A checkpoint folder is damaged: checksum mismatch, truncated or unreadable file."""


@dataclass
class Checkpoint:
    """A complete checkpoint folder and the step it was written after."""

    path: Path
    step: int


def checkpoint_folder_name(step: int) -> str:
    """``step_NNNNNNNN``: the folder name of the checkpoint written after ``step``."""
    return f"step_{step:08d}"


def checkpoint_run(folder: Path) -> Path | None:
    """The run folder when ``folder`` is one of its checkpoint folders (``RUN/checkpoints/step_N``
    with weights, under a run that has a ``config.json``), else None."""
    folder = Path(folder)
    if (folder / CONFIG_FILE).is_file() or not (folder / WEIGHTS_FILE).is_file():
        return None
    run = folder.parent.parent
    return run if (run / CONFIG_FILE).is_file() else None


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


def list_checkpoints(run_dir: Path) -> list[Checkpoint]:
    """Complete checkpoint folders, oldest first (temporary siblings of a killed write are ignored)."""
    root = Path(run_dir) / CHECKPOINT_DIR
    out = []
    if root.is_dir():
        for p in root.iterdir():
            m = _NAME.match(p.name)
            if m and all((p / name).is_file() for name in CHECKPOINT_FILES):
                out.append(Checkpoint(p, int(m.group(1))))
    return sorted(out, key=lambda c: c.step)


def latest_checkpoint(run_dir: Path) -> Checkpoint | None:
    cks = list_checkpoints(run_dir)
    return cks[-1] if cks else None


def verify_checkpoint(ck: Checkpoint) -> bool:
    """Check ``ck``'s files against its ``checksums.json``; False when the folder predates checksums.

    Raises :class:`CheckpointError` naming the file and the problem: a missing or unreadable
    checksum file entry, a size or SHA-256 that differs.
    """
    sums_path = ck.path / CHECKSUM_FILE
    if not sums_path.exists():
        return False
    try:
        sums = json.loads(sums_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise CheckpointError(sums_path, f"unreadable checksums ({e})") from None
    for name in CHECKPOINT_FILES:
        entry = sums.get(name) if isinstance(sums, dict) else None
        if not isinstance(entry, dict) or not isinstance(entry.get("sha256"), str) or type(entry.get("bytes")) is not int:
            raise CheckpointError(sums_path, f"no size and sha256 for {name}")
        path = ck.path / name
        try:
            size = path.stat().st_size
            if size != entry["bytes"]:
                raise CheckpointError(path, f"is {size} bytes, its checksum says {entry['bytes']} (truncated or damaged)")
            if sha256_file(path) != entry["sha256"]:
                raise CheckpointError(path, "SHA-256 differs from checksums.json (damaged)")
        except OSError as e:
            raise CheckpointError(path, f"unreadable ({e.strerror or e})") from None
    return True


def intact_checkpoint(run_dir: Path) -> Checkpoint | None:
    """The newest checkpoint whose files match their checksums (older folders without checksums count)."""
    for ck in reversed(list_checkpoints(run_dir)):
        try:
            verify_checkpoint(ck)
        except CheckpointError:
            continue
        return ck
    return None
