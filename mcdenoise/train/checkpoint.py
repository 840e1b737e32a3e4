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

The folder layout, listing and checksum verification (standard library only) are in
:mod:`mcdenoise.io.run_folder` and re-exported here; this module writes and loads with torch.
"""

from __future__ import annotations

import json
import pickle
import shutil
import sys
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from mcdenoise.errors import OutputError
from mcdenoise.io.atomic import atomic_dir
from mcdenoise.io.run_folder import CHECKPOINT_DIR, CHECKPOINT_FILES, CHECKSUM_FILE, Checkpoint, CheckpointError, \
    checkpoint_folder_name, intact_checkpoint, latest_checkpoint, list_checkpoints, sha256_file, verify_checkpoint
from mcdenoise.io.safety import os_error

__all__ = ["CHECKPOINT_DIR", "CHECKSUM_FILE", "Checkpoint", "CheckpointError", "save_checkpoint", "latest_checkpoint",
           "load_checkpoint", "verify_checkpoint", "resume_checkpoint", "intact_checkpoint", "prune_checkpoints",
           "state_dict_for_safetensors", "sha256_file", "list_checkpoints"]


def state_dict_for_safetensors(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The model's state dict as contiguous CPU tensors that share no storage (safetensors refuses both)."""
    return {k: v.detach().to("cpu").contiguous().clone() for k, v in model.state_dict().items()}


def save_checkpoint(run_dir: Path, step: int, model: torch.nn.Module, state: dict[str, Any]) -> Checkpoint:
    """Write ``checkpoints/step_<step>/`` atomically; ``state`` must hold tensors/numbers/strings only."""
    final = Path(run_dir) / CHECKPOINT_DIR / checkpoint_folder_name(step)
    # A rerun after a kill between this step's write and the next may find it already there.
    try:
        with atomic_dir(final, overwrite=True) as tmp:
            save_file(state_dict_for_safetensors(model), str(tmp / "model.safetensors"), metadata={"step": str(step)})
            torch.save(dict(state, step=step), tmp / "state.pt")
            sums = {name: {"bytes": (tmp / name).stat().st_size, "sha256": sha256_file(tmp / name)}
                    for name in CHECKPOINT_FILES}
            (tmp / CHECKSUM_FILE).write_text(json.dumps(sums, indent=1) + "\n")
    except OutputError:
        raise
    except OSError as e:
        raise os_error(final, e, "writing the checkpoint") from None
    except (RuntimeError, SafetensorError) as e:  # torch.save/safetensors report a full disk this way
        text = " ".join(str(e).split())[:200]
        raise OutputError(final, f"writing the checkpoint failed (is the disk full? {text}); the run can be "
                                 "resumed from the previous checkpoint with --resume") from None
    return Checkpoint(final, step)


def load_checkpoint(ck: Checkpoint, model: torch.nn.Module, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Verify ``ck``, load its weights into ``model`` (strict) and return its state (``weights_only=True``).

    Raises :class:`CheckpointError` (one line naming the file) for a damaged checkpoint: checksum
    mismatch, unreadable file, non-finite weights, a state that is not a training state.
    """
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
