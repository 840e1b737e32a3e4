"""Invariants every kernel-predicting model must keep, at initialisation and with peaked kernels.

A constant image through normalised kernels must stay constant, whatever the kernels look like.
Multiplying every parameter by 2 or 3 makes the predicted kernels sharply peaked (logit gaps of
tens, as training produces); any normalisation whose shift does not cancel per output pixel
(issue 8, bugs 1-3) then drops pixels to 0 or NaN while the unscaled model still looks fine.
"""

from __future__ import annotations

import pytest
import torch

from mcdenoise.data.channels import base_name, is_variance_name
from mcdenoise.models.registry import build_model, synthetic_batch

#: Every model whose output is a normalised filter of its input radiance. Not dpcn: it predicts
#: colours directly (no kernel), so the constant-image property does not hold for it.
KERNEL_MODELS = [
    "kpcn", "kpcn_single",
    "sbmc", "sbmc_gather", "pixel_gather", "pixel_splat",
    "layer", "layer_weighted", "layer_optimized",
    "wskp", "wskp_mr",
]


def constant_batch(model: torch.nn.Module, *, spp: int = 4, size: int = 24) -> dict[str, torch.Tensor]:
    """Radiance 1, diffuse and specular 0.5, albedo 0.5, variances 0; other features as
    :func:`synthetic_batch` makes them (so kernels still vary across the image)."""
    batch = synthetic_batch(model, batch=1, spp=spp, height=size, width=size,
                            generator=torch.Generator().manual_seed(3))
    for name, x in batch.items():
        if name == "scene_features":
            continue
        base = base_name(name)
        if is_variance_name(name):
            batch[name] = torch.zeros_like(x)
        elif base == "radiance":
            batch[name] = torch.ones_like(x)
        elif base in ("diffuse", "specular") or base.startswith("albedo"):
            batch[name] = torch.full_like(x, 0.5)
    return batch


def _scaled(model: torch.nn.Module, factor: float) -> torch.nn.Module:
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(factor)
    return model


@pytest.mark.parametrize("factor", [1.0, 2.0, 3.0])
@pytest.mark.parametrize("name", KERNEL_MODELS)
def test_constant_image_stays_constant(name: str, factor: float) -> None:
    """Catches: a per-kernel or per-neighbourhood max shift that does not cancel in the per-pixel
    normalisation (black pixels once kernels peak), an eps added after such a shift (layer
    compositing), running-sum cancellation in box filters (NaN), and kernels that do not sum to 1."""
    torch.manual_seed(0)
    model = _scaled(build_model(name, "small").eval(), factor)
    batch = constant_batch(model)
    with torch.no_grad():
        out = model(batch)
    assert torch.isfinite(out).all(), f"{name} x{factor}: non-finite output"
    err = (out - 1.0).abs().max().item()
    assert err < 1e-3, f"{name} x{factor}: constant radiance 1 came out in [{out.min():.4g}, {out.max():.4g}]"
