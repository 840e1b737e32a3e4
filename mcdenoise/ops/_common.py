"""Shared plumbing of the kernel operators: implementation switch and input checks."""

from __future__ import annotations

import contextlib
import contextvars
import math
from typing import Iterator

from torch import Tensor

__all__ = ["IMPLS", "use_impl", "resolve_impl", "check_tensor", "kernel_size_from", "get_default_impl"]

IMPLS = ("auto", "reference", "fast")

# "auto" lets every op pick its fast path; use_impl("reference") forces the plain references
# everywhere (for debugging a model against the clear versions).  A context variable scoped by a
# context manager: no caller mutates a global by hand, and threads do not see each other's choice.
_default_impl: contextvars.ContextVar[str] = contextvars.ContextVar("mcdenoise_ops_impl", default="auto")


def get_default_impl() -> str:
    """The implementation ``impl="auto"`` currently resolves against (``"auto"`` unless forced)."""
    return _default_impl.get()


@contextlib.contextmanager
def use_impl(impl: str) -> Iterator[None]:
    """Context manager forcing every op called with ``impl="auto"`` to use ``impl``.

    Example: ``with use_impl("reference"): model(batch)`` runs all kernel ops through the
    unfold-based references.
    """
    if impl not in IMPLS:
        raise ValueError(f"impl must be one of {IMPLS}, got {impl!r}")
    token = _default_impl.set(impl)
    try:
        yield
    finally:
        _default_impl.reset(token)


def resolve_impl(impl: str, op: str) -> str:
    """Map ``impl`` ("auto" | "reference" | "fast") to the implementation to run."""
    if impl not in IMPLS:
        raise ValueError(f"{op}: impl must be one of {IMPLS}, got {impl!r}")
    if impl == "auto":
        impl = _default_impl.get()
    return "fast" if impl == "auto" else impl


def check_tensor(x: object, name: str, ndim: int, shape_doc: str, op: str) -> Tensor:
    """Raise ``ValueError`` naming the expected shape unless ``x`` is a floating tensor of ``ndim`` dims."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{op}: {name} must be a torch.Tensor of shape {shape_doc}, got {type(x).__name__}")
    if x.dim() != ndim:
        raise ValueError(f"{op}: {name} must have shape {shape_doc}, got {tuple(x.shape)}")
    if not x.is_floating_point():
        raise ValueError(f"{op}: {name} must be a floating-point tensor of shape {shape_doc}, got dtype {x.dtype}")
    return x


def kernel_size_from(kk: int, name: str, shape_doc: str, op: str) -> int:
    """Side K of a square odd kernel from its number of taps K*K."""
    k = math.isqrt(kk)
    if k * k != kk or k % 2 == 0:
        raise ValueError(
            f"{op}: {name} must have shape {shape_doc} with K*K taps for an odd K, got {kk} taps"
        )
    return k


def check_same(a: Tensor, b: Tensor, names: str, op: str) -> None:
    """Both tensors on the same device with the same dtype."""
    if a.device != b.device or a.dtype != b.dtype:
        raise ValueError(
            f"{op}: {names} must share device and dtype, got {a.dtype}@{a.device} and {b.dtype}@{b.device}"
        )
