"""Kernel operators shared by the denoisers: gather, splat, importance-map kernels, multi-scale.

Every op has a plain-PyTorch reference (``*_reference``) and a memory-bounded fast path, selected
by ``impl="auto" | "reference" | "fast"``; ``with use_impl("reference"):`` forces the references
everywhere.  Kernel taps: for a K x K kernel, flat index ``i * K + j`` is offset
``(dy, dx) = (i - K//2, j - K//2)``; zero padding outside the image.  See docs/OPS.md.
"""

from mcdenoise.ops._common import get_default_impl, use_impl
from mcdenoise.ops.gather import Gather, gather, gather_fast, gather_reference
from mcdenoise.ops.importance import (
    WSKP_SIZES,
    FusedImportanceFilter,
    ImportanceFilter,
    box_sum,
    fused_importance_filter,
    importance_filter,
    importance_filter_fast,
    importance_filter_reference,
    importance_kernel_reference,
)
from mcdenoise.ops.kernels import ExpKernel, SoftmaxKernel, exp_kernel, per_destination_exp, per_pixel_exp, softmax_kernel
from mcdenoise.ops.multiscale import (
    HierarchicalFilter,
    MultiresBlend,
    build_pyramid,
    combine_levels,
    downsample2,
    hierarchical_filter,
    multires_blend,
    upsample2,
)
from mcdenoise.ops.splat import (
    Splat,
    SplatAccumulator,
    normalize_splat,
    splat,
    splat_fast,
    splat_reference,
)

__all__ = [
    "use_impl",
    "get_default_impl",
    "gather",
    "gather_reference",
    "gather_fast",
    "Gather",
    "splat",
    "splat_reference",
    "splat_fast",
    "normalize_splat",
    "Splat",
    "SplatAccumulator",
    "softmax_kernel",
    "exp_kernel",
    "per_destination_exp",
    "per_pixel_exp",
    "SoftmaxKernel",
    "ExpKernel",
    "importance_filter",
    "importance_filter_reference",
    "importance_filter_fast",
    "importance_kernel_reference",
    "box_sum",
    "fused_importance_filter",
    "ImportanceFilter",
    "FusedImportanceFilter",
    "WSKP_SIZES",
    "downsample2",
    "upsample2",
    "build_pyramid",
    "combine_levels",
    "hierarchical_filter",
    "multires_blend",
    "HierarchicalFilter",
    "MultiresBlend",
]
