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

* ``precision="bfloat16"``: every convolution trunk the model names (:meth:`Denoiser.conv_trunks`:
  U-Nets, KPCN's branches, WSKP's ImportanceNet) runs in bfloat16 and channels_last, cast once on
  the way in and back to float32 NCHW on the way out; kernel logits are exponentiated, normalised
  and applied in float32. On CPUs with native bfloat16 (AVX512-BF16, AMX) oneDNN runs these
  convolutions 2.2-4x faster than float32 NCHW (``benchmarks/bench_fast_paths.py --parts convs``); elsewhere it is emulated and slower, so
  ``"auto"`` picks it only where :func:`native_bfloat16` says so. Off by default: the error it
  adds is measured per shipped model on the test split (docs/PERFORMANCE.md), not assumed.

Paths that are always on because they are the models' only inference path (no switch needed):
banded kernel prediction and splatting with bounded memory in SBMC and the layer models (active
whenever gradients are off), the separable box-sum importance filter (WSKP), in-place
activations after convolutions, 1x1 convolutions as batched matrix products
(:class:`mcdenoise.models.blocks.PointwiseConv`).
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator

import torch
from torch import nn

__all__ = ["prepare_inference", "inference_context", "denoise_batch", "native_bfloat16", "resolve_precision",
           "ReducedPrecision", "PRECISIONS", "convert_layout"]

#: Values of ``precision`` (``auto``: bfloat16 where :func:`native_bfloat16`, else float32).
PRECISIONS = ("float32", "bfloat16", "auto")


def native_bfloat16(device: str | torch.device = "cpu") -> bool:
    """Does ``device`` compute bfloat16 convolutions natively (CUDA compute >= 8.0; x86 CPUs
    with AVX512-BF16 or AMX-BF16)?"""
    dev = torch.device(device)
    if dev.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.get_device_capability(dev)[0] >= 8
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags


def resolve_precision(precision: str | None, device: str | torch.device = "cpu") -> str:
    """``float32`` or ``bfloat16`` for a ``precision`` of :data:`PRECISIONS` (None = float32)."""
    if precision in (None, "float32"):
        return "float32"
    if precision == "bfloat16":
        return "bfloat16"
    if precision == "auto":
        return "bfloat16" if native_bfloat16(device) else "float32"
    raise ValueError(f"precision {precision!r}: expected one of {', '.join(PRECISIONS)}")


def convert_layout(t: torch.Tensor, dtype: torch.dtype, memory_format: torch.memory_format,
                   band_bytes: int = 2 << 20) -> torch.Tensor:
    """``t.to(dtype, memory_format=...)`` for a 4-D tensor, copied in row bands of about
    ``band_bytes``: a whole-image NCHW <-> NHWC copy misses the cache on every element, a band at
    a time stays in it. A narrowing cast runs first, in the source layout (element-wise, fast),
    so the transposing copy moves the smaller elements. Against a plain ``.to()`` at 1080p
    (``benchmarks/bench_fast_paths.py --parts layout``): 81 bfloat16 channels_last -> float32
    NCHW 705 -> 177 ms, 27 float32 NCHW -> bfloat16 channels_last 77 -> 47 ms."""
    if t.dim() != 4 or t.is_contiguous(memory_format=memory_format):
        return t.to(dtype)
    if torch.empty((), dtype=dtype).element_size() < t.element_size():
        t = t.to(dtype)
    b, c, h, w = t.shape
    out = torch.empty((b, c, h, w), dtype=dtype, device=t.device, memory_format=memory_format)
    if t.device.type != "cpu":
        return out.copy_(t)
    rows = max(1, band_bytes // max(1, b * c * w * t.element_size()))
    for r in range(0, h, rows):
        out[:, :, r : r + rows].copy_(t[:, :, r : r + rows])
    return out


class ReducedPrecision(nn.Module):
    """Runs ``inner`` in ``dtype`` and channels_last: 4-D floating inputs are cast once on the way
    in, outputs (a tensor or a tuple/list of them) back to the input's dtype and NCHW."""

    def __init__(self, inner: nn.Module, dtype: torch.dtype = torch.bfloat16, restore_output: bool = True) -> None:
        super().__init__()
        self.inner = inner.to(dtype=dtype, memory_format=torch.channels_last)
        self.dtype = dtype
        # False: return the inner output as it is (the caller converts it, a row band at a time).
        self.restore_output = restore_output

    def forward(self, *args: Any, **kwargs: Any) -> Any:
        ref = next((a for a in args if isinstance(a, torch.Tensor) and a.is_floating_point()), None)
        back = ref.dtype if ref is not None else torch.float32

        def down(a: Any) -> Any:
            if isinstance(a, torch.Tensor) and a.is_floating_point():
                return convert_layout(a, self.dtype, torch.channels_last) if a.dim() == 4 else a.to(self.dtype)
            return a

        def up(a: Any) -> Any:
            if isinstance(a, torch.Tensor) and a.is_floating_point():
                return convert_layout(a, back, torch.contiguous_format) if a.dim() == 4 else a.to(back)
            if isinstance(a, (tuple, list)):
                return type(a)(up(v) for v in a)
            return a

        out = self.inner(*(down(a) for a in args), **{k: down(v) for k, v in kwargs.items()})
        return up(out) if self.restore_output else out


def _restores_layout(model: nn.Module, name: str) -> bool:
    """Whether trunk ``name``'s output must come back in the contiguous layout: the nearest module
    on its path that declares ``trunk_outputs_any_layout`` decides (a model nested in another, such
    as a combiner's kernel candidate, keeps its own rule); none declares it: restore."""
    parts = name.split(".")
    for i in range(len(parts) - 1, -1, -1):
        owner = model.get_submodule(".".join(parts[:i])) if i else model
        if hasattr(owner, "trunk_outputs_any_layout"):
            return not owner.trunk_outputs_any_layout
    return True


def _wrap_trunks(model: nn.Module, dtype: torch.dtype) -> int:
    names = model.conv_trunks() if hasattr(model, "conv_trunks") else []
    for name in names:
        restore = _restores_layout(model, name)
        parent_name, _, attr = name.rpartition(".")
        parent = model.get_submodule(parent_name) if parent_name else model
        child = parent.get_submodule(attr)
        if not isinstance(child, ReducedPrecision):
            wrapped = ReducedPrecision(child, dtype, restore_output=restore)
            if attr.isdigit():
                parent[int(attr)] = wrapped  # type: ignore[index]
            else:
                setattr(parent, attr, wrapped)
    return len(names)


def prepare_inference(model: nn.Module, *, fast: bool = True, channels_last: bool | None = None,
                      precision: str | None = None) -> nn.Module:
    """Put ``model`` in eval mode and, with ``fast``, in its folded inference form (in place).

    Args:
        model: a registered :class:`~mcdenoise.models.registry.Denoiser` (weights loaded first:
            a folded WSKP has different state-dict keys).
        fast: fold RepVGG blocks and apply ``channels_last`` (see the module docstring).
        channels_last: None = on CUDA only; True/False to force.
        precision: ``float32`` (default), ``bfloat16`` (convolution trunks in bfloat16 and
            channels_last) or ``auto`` (bfloat16 where the device computes it natively); only
            with ``fast``.

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
    p = next(model.parameters(), None)
    if resolve_precision(precision, p.device if p is not None else "cpu") == "bfloat16":
        _wrap_trunks(model, torch.bfloat16)
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
