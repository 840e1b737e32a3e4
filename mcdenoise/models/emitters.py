"""Emitter pixels: where an albedo buffer holds something that is not a reflectance (issue 21).

Our renderer writes albedo in [0, 1] and 0 on a miss. Other renderers do not: Cycles writes the
emission colour into ``Denoising Albedo`` where a light is seen directly or in a mirror (values
up to 1651 in issue 21's scenes) and the background colour on sky pixels (up to 20), with normal 0
on the sky (a light seen directly keeps its own normal and depth in Blender 4.5). A model that
demodulates by the albedo (``wskp``, ``wskp_mr``, ``kpcn``'s diffuse branch) divides by that value
and multiplies the filtered neighbourhood back by it: a 1-2 px reflection of a point light became
a 7x7 block of 10^5 (reference maximum 141).

The rule, the same in every model that reads an albedo:

1. An **emitter pixel** is one where any albedo value exceeds 1: any channel of any albedo buffer
   the model reads (``albedo``, ``albedo_diffuse``), and for per-sample inputs any sample.
   A reflectance above 1 does not exist, so nothing that is one is caught.
2. Its **output is its input radiance**, unfiltered (the pixel mean for per-sample inputs): a light
   seen directly is the brightest pixel around and has little noise where it is fully covered;
   filtering it spreads it into dark neighbours, where the relative error is large.
3. Every albedo buffer **reads 1 there**, in the features and in the demodulation alike (the value
   divided by is the one multiplied back): never a huge or tiny value divided by and multiplied
   back. (0, our miss convention, would let a partly covered pixel's ``1 - |normal|`` term be the
   divisor, an amplification of up to 20x in ``wskp``.)
4. Its **colour is filled from its neighbours** in what the model sees (:func:`fill_emitters`:
   radiance, diffuse, specular and their variances, every sample): a light is not a sample of the
   surfaces around it, and its 10^4 spread by a kernel weight of 0.02 is a halo of 200 on
   surfaces of 1 (on a synthetic image, shipped wskp, kpcn and layer put 260-1600 around one
   such pixel).
   The fill is normalised 3x3 averaging of the pixels that are not emitters, repeated inward
   :data:`FILL_STEPS` times (deeper pixels of a large light read 0: no kernel reaches them from
   outside).

Where every albedo value is <= 1 every step is the identity, bit for bit: data in our own
convention gives exactly what it gave before (``tests/test_model_highlights.py``), and costs one
pass over the albedo (no copy). Steps 2 and 3 are recorded unconditionally in traced exports
(ONNX, TorchScript); the fill is left out there, as it runs only when an image has an emitter
pixel (a light in an exported model's input is passed through but may bleed into its neighbours).

Not chosen: clipping the albedo to [0, 1] (issue 21: it still filters the light pixel with its
neighbours and made the room scene 6-15x worse); a ``normal == 0`` test (our misses have albedo 0
there and are handled by :func:`mcdenoise.models.wskp.effective_albedo`; Blender's dim skies, albedo
<= 1 with normal 0, are too: their demodulation amplifies at most 1 + 1 / threshold).
Models that do not divide by an albedo keep the bound by design: the sample models' kernels are
normalised (the output is a convex combination of input radiance) and ``combine`` clamps its
albedo feature to [0, 1] and mixes its candidates convexly.
"""

from __future__ import annotations

from typing import Mapping

import torch
import torch.nn.functional as F

__all__ = ["ALBEDO_CHANNELS", "FILLED_CHANNELS", "FILL_STEPS", "emitter_mask", "as_reflectance",
           "batch_emitter_mask", "fill_from_neighbours", "fill_emitters", "pass_through"]

#: The albedo buffers of the channel vocabulary (:mod:`mcdenoise.data.channels`).
ALBEDO_CHANNELS = ("albedo", "albedo_diffuse")
#: The colour buffers (and their variances) filled at emitter pixels by :func:`fill_emitters`.
FILLED_CHANNELS = ("radiance", "diffuse", "specular",
                   "radiance_variance", "diffuse_variance", "specular_variance")
#: Inward steps of the fill: at least the largest kernel radius of any preset (sbmc paper: 10).
FILL_STEPS = 16


def emitter_mask(albedo: torch.Tensor) -> torch.Tensor:
    """Emitter pixels of one albedo buffer: ``(B, 3, H, W)`` or per-sample ``(B, S, 3, H, W)`` ->
    ``(B, 1, H, W)`` bool, True where any channel (any sample) exceeds 1."""
    if albedo.dim() == 5:
        return albedo.amax(dim=(1, 2)).unsqueeze(1) > 1
    if albedo.dim() == 4:
        return albedo.amax(dim=1, keepdim=True) > 1
    raise ValueError(f"emitter_mask: expected albedo of shape (B, 3, H, W) or (B, S, 3, H, W), "
                     f"got {tuple(albedo.shape)}")


def as_reflectance(albedo: torch.Tensor) -> torch.Tensor:
    """``albedo`` with every value of its emitter pixels (:func:`emitter_mask`) set to 1; the
    same values elsewhere (bit for bit). Shape as given."""
    mask = emitter_mask(albedo)
    if not _tracing() and not bool(mask.any()):
        return albedo  # nothing to change: no copy (the usual case, every image of our renderer)
    if albedo.dim() == 5:
        mask = mask.unsqueeze(1)  # (B, 1, 1, H, W) over samples and channels
    return albedo.masked_fill(mask, 1.0)


def batch_emitter_mask(batch: Mapping[str, torch.Tensor], names: tuple[str, ...] | list[str]) -> torch.Tensor | None:
    """Union of :func:`emitter_mask` over the albedo buffers among ``names`` (the channels a model
    reads) that ``batch`` holds: ``(B, 1, H, W)`` bool, or None when it holds none."""
    mask = None
    for name in ALBEDO_CHANNELS:
        if name in names and name in batch:
            m = emitter_mask(batch[name])
            mask = m if mask is None else mask | m
    return mask


def pass_through(out: torch.Tensor, radiance: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """``out`` (B, 3, H, W) with the input ``radiance`` at emitter pixels: ``radiance`` is
    ``(B, 3, H, W)`` or per-sample ``(B, S, 3, H, W)`` (its mean over samples is used)."""
    if mask is None or (not _tracing() and not bool(mask.any())):
        return out
    if radiance.dim() == 5:
        radiance = radiance.mean(dim=1)
    return torch.where(mask, radiance.to(out.dtype), out)


def fill_from_neighbours(x: torch.Tensor, mask: torch.Tensor, steps: int = FILL_STEPS) -> torch.Tensor:
    """``x`` (B, C, H, W) or per-sample (B, S, C, H, W) with the pixels of ``mask`` (B, 1, H, W)
    replaced by the mean of their 3x3 neighbours outside it, repeated ``steps`` times inward
    (each step fills the pixels next to a filled one); pixels still unfilled read 0."""
    shape = x.shape
    flat = x.reshape(shape[0], -1, *shape[-2:])
    known = (~mask).to(flat.dtype)
    v = torch.where(mask, torch.zeros((), dtype=flat.dtype, device=flat.device), flat)
    for _ in range(steps):
        todo = known == 0
        if not bool(todo.any()):
            break
        num = F.avg_pool2d(v * known, 3, stride=1, padding=1, divisor_override=1)
        den = F.avg_pool2d(known, 3, stride=1, padding=1, divisor_override=1)
        reach = todo & (den > 0)
        v = torch.where(reach, num / den.clamp_min(1), v)
        known = torch.where(reach, torch.ones_like(known), known)
    return v.reshape(shape)


def _tracing() -> bool:
    """Inside a trace or an export (TorchScript tracing, torch.export / ONNX, torch.compile), where
    a branch on the data cannot be recorded."""
    return torch.jit.is_tracing() or torch.compiler.is_compiling() or torch.onnx.is_in_onnx_export()


def fill_emitters(batch: Mapping[str, torch.Tensor], mask: torch.Tensor | None) -> Mapping[str, torch.Tensor]:
    """``batch`` with every :data:`FILLED_CHANNELS` buffer filled at the emitter pixels of ``mask``
    (:func:`fill_from_neighbours`). The same object, untouched, when there are none (or ``mask``
    is None), and inside a trace (see the module docstring)."""
    if mask is None or _tracing() or not bool(mask.any()):
        return batch
    out = dict(batch)
    for name in FILLED_CHANNELS:
        if name in out:
            out[name] = fill_from_neighbours(out[name], mask)
    return out
