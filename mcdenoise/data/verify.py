"""Full integrity check of image folders and datasets: every block and file against the checksums
meta.json records (``mcdenoise dataset --verify``, ``--merge`` and resume use it)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mcdenoise.data.checksums import block_crcs
from mcdenoise.data.image_folder import ImageFolder
from mcdenoise.errors import FormatError

__all__ = ["verify_image", "find_image_folders", "verify_manifests", "verify_tree"]


def verify_image(folder: str | os.PathLike, *, full: bool = True) -> str | None:
    """None when the image folder is intact, else one line naming the damaged file and the problem.

    Opening checks meta.json, the samples header and file sizes (a truncated samples.bin fails
    here); ``full`` also reads every byte: each samples block and each EXR against its CRC-32.
    """
    try:
        img = ImageFolder(folder)
        if not full:
            return None
        r = img.samples
        if r is not None:
            table = r.block_table()
            if table is not None:
                for ci, name in enumerate(r.channels):
                    bad = np.argwhere(block_crcs(r.memmap(name)) != table[ci])
                    if bad.size:
                        ty, tx, s = (int(v) for v in bad[0])
                        t = r.tile
                        return (f"{r.path}: damaged: {len(bad)} block(s) of channel {name!r} fail their checksum, first "
                                f"sample {s} of the tile at pixels y={ty * t}..{ty * t + t - 1}, x={tx * t}..{tx * t + t - 1}")
        for key in ("noisy", "reference"):
            rel = img._files.get(key)
            if rel:
                img._verify_file(img.path / rel)
    except FormatError as e:
        return str(e)
    except OSError as e:
        return f"{folder}: unreadable ({e.strerror or e})"
    return None


def find_image_folders(root: str | os.PathLike) -> list[Path]:
    """Every image folder (a folder holding meta.json) under ``root``, hidden temporaries skipped."""
    root = Path(root)
    out: list[Path] = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        if "meta.json" in filenames:
            out.append(Path(dirpath))
            dirnames[:] = []
    return out


def verify_manifests(root: str | os.PathLike) -> list[str]:
    """One line per dataset under ``root`` whose manifest.json is invalid (bad split, a path listed
    twice, a scene in two splits, a listed image missing...)."""
    from mcdenoise.data.dataset import Dataset

    problems = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        if "manifest.json" in filenames:
            try:
                Dataset(dirpath)
            except FormatError as e:
                problems.append(str(e))
        if "meta.json" in filenames:
            dirnames[:] = []
    return problems


def verify_tree(root: str | os.PathLike, *, full: bool = True) -> tuple[int, list[str]]:
    """(number of image folders checked, one line per damaged image or invalid manifest) under ``root``."""
    folders = find_image_folders(root)
    problems = [p for p in (verify_image(f, full=full) for f in folders) if p is not None]
    return len(folders), verify_manifests(root) + problems
