"""Atomic output: write under a temporary sibling name, then rename over the final name."""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

__all__ = ["atomic_file", "atomic_dir", "temp_sibling"]


def temp_sibling(path: str | os.PathLike, tag: str = "tmp") -> Path:
    """A unique hidden name in the same folder as ``path`` (same file system, so rename is atomic).

    The original suffix is kept last because some writers pick the format from the extension.
    """
    p = Path(path)
    return p.with_name(f".{p.stem}.{tag}-{os.getpid()}-{uuid.uuid4().hex[:8]}{p.suffix}")


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path to write; on success it replaces ``path``, on error it is removed."""
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(final)
    try:
        yield tmp
        os.replace(tmp, final)
    finally:
        if tmp.exists():
            tmp.unlink()


def _remove_tree(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    elif p.exists() or p.is_symlink():
        p.unlink()


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary folder to fill; on success it is renamed to ``path``.

    With ``overwrite`` an existing ``path`` is moved aside first and deleted after the rename, so
    readers see either the old folder or the new one, never a half-written one.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    if final.exists() and not overwrite:
        raise FileExistsError(f"{final}: already exists (pass overwrite=True to replace it)")
    tmp = temp_sibling(final, "tmp")
    tmp.mkdir()
    try:
        yield tmp
        old = None
        if final.exists():
            if not overwrite:
                raise FileExistsError(f"{final}: appeared while writing (pass overwrite=True to replace it)")
            old = temp_sibling(final, "old")
            os.replace(final, old)
        os.replace(tmp, final)
        if old is not None:
            _remove_tree(old)
    finally:
        if tmp.exists():
            _remove_tree(tmp)
