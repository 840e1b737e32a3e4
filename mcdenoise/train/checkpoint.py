"""Checkpoints of a run folder: ``checkpoints/step_NNNNNNNN/{model.safetensors, state.pt}``.

Each checkpoint folder is written whole under a temporary name and renamed into place
(:func:`mcdenoise.io.atomic.atomic_dir`), so a kill at any moment leaves either no folder or a
complete one; the newest complete folder is the one to resume from. Weights are safetensors (never
unpickled); the rest (Adam moments, RNG states, step and counters) is a torch file of tensors,
numbers and strings only, so it loads with ``torch.load(weights_only=True)``. The learning-rate
schedule is a pure function of the step, so the step is all the scheduler state there is.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file

from mcdenoise.io.atomic import atomic_dir

__all__ = ["CHECKPOINT_DIR", "Checkpoint", "save_checkpoint", "latest_checkpoint", "load_checkpoint", "prune_checkpoints",
           "state_dict_for_safetensors"]

CHECKPOINT_DIR = "checkpoints"
_NAME = re.compile(r"^step_(\d{8})$")


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
    return Checkpoint(final, step)


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


def load_checkpoint(ck: Checkpoint, model: torch.nn.Module, device: torch.device | str = "cpu") -> dict[str, Any]:
    """Load weights into ``model`` (strict) and return the state dict (``weights_only=True``)."""
    model.load_state_dict(load_file(str(ck.path / "model.safetensors"), device=str(device)))
    return torch.load(ck.path / "state.pt", map_location="cpu", weights_only=True)


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
