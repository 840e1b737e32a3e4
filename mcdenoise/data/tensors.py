"""Turn an image folder into the batch dict a model reads (see ``mcdenoise/models/registry.py``).

Kept apart from the on-disk reader (``format.py``) and from crop sampling, as STYLE.md item 6 asks:
this is the one place that knows how stored buffers become model tensors.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from mcdenoise.data.channels import base_name
from mcdenoise.data.format import pixel_stats
from mcdenoise.errors import FormatError

__all__ = ["image_batch", "input_arrays"]


def input_arrays(
    folder: "object",
    channels: Sequence[str],
    input_kind: str,
    *,
    spp: int | None = None,
) -> dict[str, np.ndarray]:
    """A model's inputs for one whole image from its first ``spp`` stored samples (no batch axis).

    The one place that turns "k samples of this image" into model inputs, shared by validation
    (:func:`mcdenoise.train.data.validation_batches`) and evaluation (:mod:`mcdenoise.eval`), so
    both see exactly the same inputs.

    Args:
        folder: an :class:`mcdenoise.data.format.ImageFolder`.
        channels: names to return (``scene_features`` is ignored; see ``meta.scene_feature_vector``).
        input_kind: ``"samples"`` -> name -> ``(k, C, H, W)`` float32, samples ``0..k-1``;
            ``"pixels"`` -> name -> ``(C, H, W)`` float32 means and ``*_variance`` (variance of the
            mean, :func:`~mcdenoise.data.format.pixel_stats`) over samples ``0..k-1``. With all
            stored samples (``spp`` None or the stored count) they come from ``noisy.exr``, which
            holds the same numbers.
        spp: ``k``, 1 <= k <= the stored spp; None = all stored samples.
    """
    from mcdenoise.data.oidn_input import oidn_for, split_oidn

    names, want_oidn = split_oidn([c for c in channels if c != "scene_features"])
    if want_oidn:
        out = input_arrays(folder, names, input_kind, spp=spp)
        for ch in want_oidn:
            out[ch] = oidn_for(folder, spp, channel=ch)
        return out
    total = folder.meta.spp
    k = total if spp is None else int(spp)
    if not 1 <= k <= total:
        raise ValueError(f"{folder.path}: asked for {k} samples, the image stores {total}")
    if input_kind not in ("samples", "pixels"):
        raise ValueError(f"input_kind must be 'samples' or 'pixels', got {input_kind!r}")
    if input_kind == "pixels" and k == total:
        return folder.read_noisy(names)
    if folder.samples is None:
        raise FormatError(folder.path, f"{k} of {total} samples asked for, but the folder has no samples file")
    idx = list(range(k))
    if input_kind == "samples":
        return folder.samples.read(names, samples=idx)
    bases = list(dict.fromkeys(base_name(c) for c in names))
    smp = folder.samples.read(bases, samples=idx)
    stats: dict[str, np.ndarray] = {}
    for b in bases:
        stats[b], stats[b + "_variance"] = pixel_stats(smp[b])
    return {c: stats[c] for c in names}


def image_batch(
    folder: "object",
    channels: Sequence[str],
    input_kind: str,
    *,
    crop: tuple[int, int, int, int] | None = None,
    samples: slice | Sequence[int] | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, torch.Tensor]:
    """Read what a model needs from one image folder as a batch of one.

    Args:
        folder: an :class:`mcdenoise.data.format.ImageFolder`.
        channels: the model's ``required_channels()``.
        input_kind: ``"samples"`` -> tensors ``(1, S, C, h, w)`` plus ``scene_features (1, F)``;
            ``"pixels"`` -> tensors ``(1, C, h, w)`` from ``noisy.exr`` (means and ``*_variance``).
        crop: ``(y0, x0, h, w)``; only those bytes are read.
        samples: subset of sample indices (sample models only).
    """
    names = [c for c in channels if c != "scene_features"]
    if input_kind == "samples":
        reader = folder.samples
        if reader is None:
            raise FormatError(folder.path, "this model needs per-sample buffers but the folder has no samples file")
        arrays = reader.read(names, crop=crop, samples=samples)
        out = {k: torch.from_numpy(np.ascontiguousarray(v))[None].to(device) for k, v in arrays.items()}
        feats = folder.meta.scene_feature_vector()
        out["scene_features"] = torch.from_numpy(feats)[None].to(device)
        return out
    if input_kind == "pixels":
        arrays = folder.read_noisy(names, crop=crop)
        return {k: torch.from_numpy(np.ascontiguousarray(v))[None].to(device) for k, v in arrays.items()}
    raise ValueError(f"input_kind must be 'samples' or 'pixels', got {input_kind!r}")
