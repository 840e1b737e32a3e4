"""Turn an image folder into the batch dict a model reads (see ``mcdenoise/models/registry.py``).

Kept apart from the on-disk reader (``format.py``) and from crop sampling, as STYLE.md item 6 asks:
this is the one place that knows how stored buffers become model tensors.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from mcdenoise.errors import FormatError

__all__ = ["image_batch"]


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
