"""The fast inference switch shared by ``mcdenoise bench``, ``eval`` and ``denoise``.

``prepare_inference(model, fast=True)`` turns a (trained) model into its inference form and
``inference_context(fast=True)`` is the context to call it in. With ``fast=False`` both give the
plain reference: eval mode under ``torch.no_grad``, nothing folded. What ``fast`` changes, each
checked against the reference in ``tests/test_fast_paths.py`` (float64, so only the algebra is
tested, not float32 rounding):

* ``torch.inference_mode`` instead of ``no_grad``: no version counters or autograd metadata on
  any tensor (outputs cannot enter a later autograd graph: call ``.clone()`` if they must);
* RepVGG re-parameterisation for models that have ``reparameterize()`` (WSKP): the 5x5, 3x3,
  1x1 and identity branches with their eval-mode BatchNorms fold into one 5x5 conv per block, as
  the paper times it (4 convolutions and 4 BNs per block become 1 convolution);
* ``channels_last`` weights, on CUDA only by default (``channels_last=None``): cuDNN's NHWC
  kernels use tensor cores; on the CPU the oneDNN paths for our narrow (8-128 channel) layers
  gain little and the permutes around every non-conv op cost, so it is off there unless asked.

Paths that are always on because they are the models' only inference path (no switch needed):
banded kernel prediction and splatting with bounded memory in SBMC and the layer models (active
whenever gradients are off), the separable box-sum importance filter (WSKP), in-place
activations after convolutions.
"""

from __future__ import annotations

import contextlib
from typing import Iterator

import torch
from torch import nn

__all__ = ["prepare_inference", "inference_context", "denoise_batch"]


def prepare_inference(model: nn.Module, *, fast: bool = True, channels_last: bool | None = None) -> nn.Module:
    """Put ``model`` in eval mode and, with ``fast``, in its folded inference form (in place).

    Args:
        model: a registered :class:`~mcdenoise.models.registry.Denoiser` (weights loaded first:
            a folded WSKP has different state-dict keys).
        fast: fold RepVGG blocks and apply ``channels_last`` (see the module docstring).
        channels_last: None = on CUDA only; True/False to force.

    Returns:
        The same module, for chaining.
    """
    model.eval()
    if not fast:
        return model
    fold = getattr(model, "reparameterize", None)
    if callable(fold):
        fold()
    if channels_last is None:
        p = next(model.parameters(), None)
        channels_last = p is not None and p.device.type == "cuda"
    if channels_last:
        model.to(memory_format=torch.channels_last)
    return model


@contextlib.contextmanager
def inference_context(fast: bool = True) -> Iterator[None]:
    """``torch.inference_mode()`` when ``fast``, else ``torch.no_grad()`` (the reference)."""
    with (torch.inference_mode() if fast else torch.no_grad()):
        yield


def denoise_batch(model: nn.Module, batch: dict[str, torch.Tensor], *, fast: bool = True) -> torch.Tensor:
    """``model(batch)`` in :func:`inference_context`: (B, 3, H, W) radiance."""
    with inference_context(fast):
        return model(batch)
