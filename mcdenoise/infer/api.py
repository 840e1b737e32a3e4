"""``mcdenoise.denoise``: the Python API, on numpy arrays or torch tensors.

Arrays may be channel-first ``(C, H, W)`` or channel-last ``(H, W, C)``; ``color`` decides
(``(3, H, W)`` is channel-first, ``(H, W, 3)`` channel-last, a ``(3, H, 3)`` image is read as
channel-first) and every other buffer follows it (single-channel ones may also be ``(H, W)``;
``samples`` are ``(S, C, H, W)`` or ``(S, H, W, C)``). Any stride and float dtype is accepted; the
model computes in float32 and the result comes back in ``color``'s kind (numpy or torch), dtype,
layout and (torch) device.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np
import torch

from mcdenoise.infer.choose import choose_model
from mcdenoise.infer.memory import parse_memory
from mcdenoise.infer.run import default_device, denoise_inputs, describe_plan
from mcdenoise.infer.sources import InputError, from_arrays
from mcdenoise.models.registry import Denoiser

__all__ = ["denoise"]

log = logging.getLogger("mcdenoise.denoise")


def _to_numpy(x: Any, what: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        if not x.dtype.is_floating_point:
            raise InputError(f"{what}: expected a float tensor, got {x.dtype}")
        return x.detach().to("cpu", torch.float32).numpy()
    a = np.asarray(x)
    if a.dtype.kind != "f":
        raise InputError(f"{what}: expected a float array, got dtype {a.dtype}")
    return a.astype(np.float32, copy=False)


def _channel_first(a: np.ndarray, last: bool, what: str, sample_dim: bool = False) -> np.ndarray:
    """Move the channel axis first (after the sample axis); a 2-D image gains one channel."""
    lead = 1 if sample_dim else 0
    if a.ndim == lead + 2:
        return np.expand_dims(a, lead)
    if a.ndim != lead + 3:
        want = "(S, C, H, W)" if sample_dim else "(C, H, W) or (H, W, C)"
        raise InputError(f"{what}: expected {want}, got shape {a.shape}")
    return np.moveaxis(a, -1, lead) if last else a


def denoise(
    color: Any,
    albedo: Any = None,
    normal: Any = None,
    depth: Any = None,
    *,
    features: dict[str, Any] | None = None,
    samples: dict[str, Any] | None = None,
    model: str | os.PathLike | Denoiser | None = None,
    device: str | torch.device | None = None,
    max_memory: int | str | None = None,
    precision: str = "auto",
    self_ensemble: bool = False,
) -> Any:
    """Denoise one image.

    Args:
        color: noisy linear HDR radiance, ``(3, H, W)`` or ``(H, W, 3)`` (numpy or torch).
        albedo, normal: ``(3, H, W)`` (same layout as ``color``): first-hit albedo in [0, 1],
            world-space unit normal.
        depth: ``(H, W)`` or ``(1, H, W)``: distance to the first hit.
        features: other per-pixel channels by their vocabulary name (``"albedo_diffuse"``,
            ``"radiance_variance"``...; see :mod:`mcdenoise.data.channels`); ``"scene_features"``
            (5 values) gives the camera's scene features to the sample models.
        samples: per-sample buffers by vocabulary name, ``(S, C, H, W)`` (or ``(S, H, W, C)``),
            for the sample models (``sbmc``, ``layer``...).
        model: a registered name (its shipped weights), a ``.safetensors`` file, a run folder, or a
            :class:`~mcdenoise.models.registry.Denoiser`; None picks the best shipped model whose
            inputs are given, as ``mcdenoise denoise`` does.
        device: ``"cpu"``, ``"cuda"``...; None: CUDA when available.
        max_memory: budget for one tile's model call, bytes or ``"4G"``; default 4 GiB.
        precision: ``auto`` (default: bfloat16 where the device computes it natively), ``float32``
            or ``bfloat16`` for the convolution trunks of a model given by name or weights (a
            :class:`Denoiser` instance is run as it is). The shipped models' test-split metrics
            agree within 2 % between the two (docs/PERFORMANCE.md).
        self_ensemble: run the model in the 8 orientations of the image and keep the per-pixel
            median (:mod:`mcdenoise.models.symmetry`): 8x the time, fewer exploded highlights.

    Returns:
        The denoised radiance with ``color``'s kind, dtype, layout and device.

    Raises:
        InputError: missing channels (naming them), sizes that differ, wrong shapes.
    """
    is_torch = isinstance(color, torch.Tensor)
    c = _to_numpy(color, "color")
    if c.ndim != 3 or 3 not in (c.shape[0], c.shape[-1]):
        raise InputError(f"color: expected (3, H, W) or (H, W, 3), got shape {tuple(c.shape)}")
    last = c.shape[0] != 3
    conv = {}
    for name, arr in (("albedo", albedo), ("normal", normal), ("depth", depth)):
        conv[name] = None if arr is None else _channel_first(_to_numpy(arr, name), last, name)
    feats = dict(features or {})
    scene = feats.pop("scene_features", None)
    feats_np = {k: _channel_first(_to_numpy(v, k), last, f"features[{k!r}]") for k, v in feats.items()}
    samples_np = None
    if samples:
        samples_np = {k: _channel_first(_to_numpy(v, k), last, f"samples[{k!r}]", sample_dim=True)
                      for k, v in samples.items()}
    inputs = from_arrays(
        _channel_first(c, last, "color"), albedo=conv["albedo"], normal=conv["normal"], depth=conv["depth"],
        features=feats_np, samples=samples_np,
        scene_features=None if scene is None else _to_numpy(scene, "scene_features"),
    )
    dev = torch.device(device) if device is not None else default_device()
    if isinstance(model, Denoiser):
        from mcdenoise.infer.choose import missing_channels

        net = model
        missing = missing_channels(net.required_channels(), net.input_kind, inputs)
        if missing:
            raise InputError(f"model {type(net).__name__} needs channels that {inputs.label} lacks: {', '.join(missing)}")
        label = type(net).__name__
    else:
        net, info = choose_model(inputs, None if model is None else str(model), device=dev, precision=precision)
        label = f"{info['name']} ({info['preset']}, {info['source']}: {info['why']})"
    budget = None if max_memory is None else parse_memory(max_memory)
    out, run = denoise_inputs(inputs, net, device=dev, max_memory=budget, progress=False, self_ensemble=self_ensemble)
    log.info("denoised with %s reading %s; %s on %s%s", label, ", ".join(run.channels), describe_plan(run.plan), dev,
             f", self-ensemble of {run.orientations} orientations" if run.orientations > 1
             else (", self-ensemble not applied (OIDN runs once)" if self_ensemble else ""))
    if last:
        out = np.moveaxis(out, 0, -1)
    if is_torch:
        return torch.from_numpy(np.ascontiguousarray(out)).to(device=color.device, dtype=color.dtype)
    dtype = np.asarray(color).dtype
    return np.ascontiguousarray(out).astype(dtype, copy=False)
