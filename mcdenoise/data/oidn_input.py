"""The derived channels ``oidn`` and ``oidn_pf``: Open Image Denoise 2.5.1's output for an image's
first ``k`` samples -- with the guides as they are (``oidn``), and with the guides prefiltered by
OIDN ``fast`` first and passed as clean (``oidn_pf``, OIDN's documented best mode for noisy guides).

Computed from the same inputs a pixel model gets (the mean colour, albedo and normal of samples
``0..k-1``; all stored samples = ``noisy.exr``) and cached once per image, ``k`` and OIDN version
under the dataset's ``.cache/oidn-<version>/`` folder, so training a combiner (issue 20) pays for
OIDN once per image and sample count. Cache files are written atomically; an unreadable one is
computed again. Outside a dataset (an image folder on its own) nothing is written.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

__all__ = ["OIDN_CHANNEL", "OIDN_CHANNELS", "oidn_for", "oidn_guides", "split_oidn"]

OIDN_CHANNEL = "oidn"
#: Derived channel -> quality OIDN prefilters the guides with (None: guides as they are).
OIDN_CHANNELS: dict[str, str | None] = {"oidn": None, "oidn_pf": "fast"}
#: How far up from an image folder a dataset's manifest.json is looked for.
_MAX_UP = 3


def _dataset_root(path: Path) -> Path | None:
    p = path.resolve()
    for _ in range(_MAX_UP):
        p = p.parent
        if (p / "manifest.json").is_file():
            return p
    return None


def oidn_guides(pixels: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The guides OIDN can use from ``pixels``: albedo when present, normal only beside albedo."""
    if "albedo" not in pixels:
        return {}
    return {k: pixels[k] for k in ("albedo", "normal") if k in pixels}


def split_oidn(names: list[str]) -> tuple[list[str], list[str]]:
    """``names`` without the derived OIDN channels, and those asked for (in order; empty: none)."""
    rest = [n for n in names if n not in OIDN_CHANNELS]
    return rest, [n for n in names if n in OIDN_CHANNELS]


def oidn_for(folder: object, k: int | None = None, *, quality: str = "high", channel: str = OIDN_CHANNEL) -> np.ndarray:
    """``(3, H, W)`` float32 OIDN output (derived ``channel``, see :data:`OIDN_CHANNELS`) for the
    first ``k`` samples of image folder ``folder``."""
    from mcdenoise.data.format import pixel_stats
    from mcdenoise.eval.oidn import oidn_denoise, version

    meta = folder.meta  # type: ignore[attr-defined]
    k = meta.spp if k is None else int(k)
    if channel not in OIDN_CHANNELS:
        raise ValueError(f"not a derived OIDN channel: {channel!r}")
    prefilter = OIDN_CHANNELS[channel]
    # the plain channel keeps its pre-existing cache name
    stem = f"{quality}_spp{k}" if prefilter is None else f"{quality}_pf-{prefilter}_spp{k}"
    root = _dataset_root(Path(folder.path))  # type: ignore[attr-defined]
    cache = None
    if root is not None:
        rel = Path(folder.path).resolve().relative_to(root)  # type: ignore[attr-defined]
        cache = root / ".cache" / f"oidn-{version()}" / rel / f"{stem}.npy"
        if cache.is_file():
            try:
                arr = np.load(cache, allow_pickle=False)
                if arr.shape == (3, meta.height, meta.width) and arr.dtype == np.float32:
                    return arr
            except (OSError, ValueError):
                pass  # damaged: computed again below
    guides = [c for c in ("albedo", "normal") if c in meta.channels]
    names = ["radiance", *guides]
    if k == meta.spp:  # noisy.exr holds the means over every stored sample
        px = folder.read_noisy(names)  # type: ignore[attr-defined]
    else:  # the same means as mcdenoise.data.tensors.input_arrays computes
        smp = folder.samples.read(names, samples=list(range(k)))  # type: ignore[attr-defined]
        px = {n: pixel_stats(v)[0] for n, v in smp.items()}
    out = oidn_denoise(px["radiance"], **oidn_guides(px), quality=quality, prefilter=prefilter)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache.with_name(f".{cache.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as f:
            np.save(f, out)
        tmp.replace(cache)
    return out
