"""Checkpoints of a run folder: ``checkpoints/step_NNNNNNNN/{model.safetensors, state.pt}``.

Each checkpoint folder is written whole under a temporary name and renamed into place
(:func:`mcdenoise.io.atomic.atomic_dir`), so a kill at any moment leaves either no folder or a
complete one; the newest complete folder is the one to resume from. Weights are safetensors (never
unpickled); the rest (Adam moments, RNG states, step and counters) is a torch file of tensors,
numbers and strings only, so it loads with ``torch.load(weights_only=True)``. The learning-rate
schedule is a pure function of the step, so the step is all the scheduler state there is.

Each folder also holds ``checksums.json`` (size and SHA-256 of both files, written last). A resume
(:func:`resume_checkpoint`) verifies it and falls back to the newest intact checkpoint, saying so in
one line: a flipped bit, a truncated or garbage file, a missing or damaged ``checksums.json`` all
make a checkpoint damaged. Folders written before checksums existed are checked by loading them.
"""

from __future__ import annotations

import hashlib
import json
import pickle
import re
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from mcdenoise.errors import FormatError
from mcdenoise.io.atomic import atomic_dir

__all__ = ["CHECKPOINT_DIR", "CHECKSUM_FILE", "Checkpoint", "CheckpointError", "save_checkpoint", "latest_checkpoint",
           "load_checkpoint", "verify_checkpoint", "resume_checkpoint", "intact_checkpoint", "prune_checkpoints",
           "state_dict_for_safetensors", "sha256_file"]

CHECKPOINT_DIR = "checkpoints"
CHECKSUM_FILE = "checksums.json"
_FILES = ("model.safetensors", "state.pt")
_NAME = re.compile(r"^step_(\d{8})$")


class CheckpointError(FormatError):
    """A checkpoint folder is damaged: checksum mismatch, truncated or unreadable file."""


@dataclass
class Checkpoint:
    """A complete checkpoint folder and the step it was written after."""

    path: Path
    step: int


def state_dict_for_safetensors(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The model's state dict as contiguous CPU tensors that share no storage (safetensors refuses both)."""
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in model.state_dict().items()}


def save_checkpoint(run_dir: Path, step: int, model: torch.nn.Module, state: dict[str, Any]) -> Checkpoint:
    """Write ``checkpoints/step_<step>/`` atomically; ``state`` must hold tensors/numbers/strings only."""
    final = Path(run_dir) / CHECKPOINT_DIR / f"step_{step:08d}"
    # A rerun after a kill between this step's write and the next may find it already there.
    with atomic_dir(final, overwrite=True) as tmp:
        save_file(state_dict_for_safetensors(model), str(tmp / "model.safetensors"), metadata={"step": str(step)})
        torch.save(dict(state, step=step), tmp / "state.pt")
        sums = {name: {"bytes": (tmp / name).stat().st_size, "sha256": sha256_file(tmp / name)} for name in _FILES}
        (tmp / CHECKSUM_FILE).write_text(json.dumps(sums, indent=1) + "\n")
    return Checkpoint(final, step)


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
            if m and (p / "model.safetensors").is_file() and (p / "state.pt").is_file():
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
    for name in _FILES:
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


def load_checkpoint(ck: Checkpoint, model: torch.nn.Module, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Verify ``ck``, load its weights into ``model`` (strict) and return its state (``weights_only=True``).

    Raises :class:`CheckpointError` (one line naming the file) for a damaged checkpoint: checksum
    mismatch, unreadable file, non-finite weights, a state that is not a training state.
    """
    from safetensors import SafetensorError

    verify_checkpoint(ck)
    weights, state_path = ck.path / "model.safetensors", ck.path / "state.pt"
    try:
        tensors = load_file(str(weights), device=str(device))
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise CheckpointError(weights, f"not a readable safetensors file ({e})") from None
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(weights, f"non-finite weights (NaN or Inf) in {', '.join(bad[:3])}")
    try:
        model.load_state_dict(tensors)
    except RuntimeError as e:
        raise CheckpointError(weights, f"weights do not fit {type(model).__name__} ({str(e).splitlines()[0][:200]})") from None
    try:
        state = torch.load(state_path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, ValueError, EOFError, pickle.UnpicklingError, KeyError, AttributeError) as e:
        raise CheckpointError(state_path, f"not a readable training state ({type(e).__name__}: "
                                          f"{str(e).strip().splitlines()[0][:200] if str(e).strip() else ''})") from None
    if not isinstance(state, dict) or not {"optimizer", "rng_cpu", "step"} <= set(state) or state["step"] != ck.step:
        raise CheckpointError(state_path, f"not the training state of step {ck.step}")
    return state


def resume_checkpoint(run_dir: Path, model: torch.nn.Module, device: torch.device | str = "cpu",
                      *, announce: bool = True) -> tuple[Checkpoint | None, dict[str, Any] | None]:
    """Load the newest intact checkpoint of ``run_dir`` into ``model``: ``(checkpoint, state)``.

    Damaged newer checkpoints are passed over, with one line on stderr naming the first problem and
    the step resumed from. ``(None, None)`` when the run has no checkpoint; a run whose every
    checkpoint is damaged raises :class:`CheckpointError`.
    """
    cks = list_checkpoints(run_dir)
    damaged: list[tuple[Checkpoint, CheckpointError]] = []
    for ck in reversed(cks):
        try:
            state = load_checkpoint(ck, model, device)
        except CheckpointError as e:
            damaged.append((ck, e))
            continue
        if damaged and announce:
            names = ", ".join(c.path.name for c, _ in damaged)
            print(f"{run_dir}: damaged checkpoint(s) {names} skipped ({damaged[0][1]}); "
                  f"resuming from the newest intact one, step {ck.step}", file=sys.stderr)
        return ck, state
    if damaged:
        raise CheckpointError(run_dir, f"every checkpoint is damaged (newest: {damaged[0][1]}); "
                                       "pass --force to start the run over")
    return None, None


def intact_checkpoint(run_dir: Path) -> Checkpoint | None:
    """The newest checkpoint whose files match their checksums (older folders without checksums count)."""
    for ck in reversed(list_checkpoints(run_dir)):
        try:
            verify_checkpoint(ck)
        except CheckpointError:
            continue
        return ck
    return None


def prune_checkpoints(run_dir: Path, keep_every: int) -> None:
    """Delete all but the newest checkpoint and those at multiples of ``keep_every``.

    Also removes temporary folders left by a write that was killed.
    """
    root = Path(run_dir) / CHECKPOINT_DIR
    cks = list_checkpoints(run_dir)
    for ck in cks[:-1]:
        if keep_every > 0 and ck.step % keep_every == 0:
            continue
        shutil.rmtree(ck.path, ignore_errors=True)
    if root.is_dir():
        for p in root.iterdir():
            if p.name.startswith(".step_"):
                shutil.rmtree(p, ignore_errors=True)
