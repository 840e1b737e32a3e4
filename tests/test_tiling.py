"""Tiled denoising equals untiled denoising for every registered model (issue 11, item 1).

Small presets, random weights, a small image cut into tiny tiles: every tile border is inside the
image, so a receptive field measured too small, a pooling grid that shifts between tiles, or a
per-tile normalisation would all show as seams.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mcdenoise.infer.receptive import alignment, measure_receptive_field, receptive_field
from mcdenoise.infer.tiling import plan_tiles, run_tiled
from mcdenoise.models import build_model, list_models, synthetic_batch

MODELS = [e.name for e in list_models()]

#: Receptive field radius (pixels) and pooling alignment of the small presets, as measured by
#: :func:`measure_receptive_field` when this was written. A model change that moves them must
#: move them here too (and tiling follows on its own).
PINNED = {
    "dpcn": (9, 1), "kpcn": (9, 1), "kpcn_single": (9, 1),
    "layer": (19, 4), "layer_weighted": (19, 4), "layer_optimized": (39, 8),
    "pixel_gather": (31, 4), "sbmc_gather": (31, 4), "pixel_splat": (35, 4), "sbmc": (35, 4),
    "wskp": (7, 1), "wskp_mr": (22, 4), "combine": (26, 4), "refine": (43, 4),
}

H, W = 29, 35  # odd sizes: the last tiles are partial and pooling pads at the border


def _run(model: torch.nn.Module, batch: dict[str, torch.Tensor], plan) -> np.ndarray:
    def read(tile):
        y0, x0, h, w = tile.window
        return {k: (v if k == "scene_features" else v[..., y0 : y0 + h, x0 : x0 + w]) for k, v in batch.items()}

    return run_tiled(model, read, plan)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_every_registered_model_is_pinned():
    """Catches a newly registered model that nobody checked for tiling."""
    assert sorted(PINNED) == sorted(MODELS)


@pytest.mark.parametrize("name", MODELS)
def test_tiled_equals_untiled(name):
    """Catches seams: overlap below the receptive field, tiles off the pooling grid, per-tile
    statistics (a depth or radiance range taken per input) -- any of them breaks 1e-4."""
    torch.manual_seed(0)
    model = build_model(name, "small").eval()
    rf = receptive_field(model)  # measured on the float32 model, as denoise does
    model = model.double()  # float64: float32 rounding differs between CPUs' conv kernels (issue 18)
    batch = synthetic_batch(model, spp=2, height=H, width=W, dtype=torch.float64)
    with torch.no_grad():
        whole = model(batch)[0].numpy()
    plan = plan_tiles(H, W, receptive=rf, align=alignment(model), core=12)
    assert len(plan) >= 6 and plan.overlap > 0
    assert _rel(_run(model, batch, plan), whole) < 1e-4


@pytest.mark.parametrize("name", MODELS)
def test_receptive_field_is_pinned(name):
    """Catches a change of architecture that changes how far a model looks, unnoticed."""
    model = build_model(name, "small")
    # receptive_field caches measure_receptive_field per configuration: the tiled test reuses it.
    assert (receptive_field(model), alignment(model)) == PINNED[name]


def test_measured_receptive_field_is_tight():
    """Catches a receptive field measured too large to matter: 3 pixels less overlap must seam."""
    torch.manual_seed(0)
    model = build_model("wskp", "small").eval()
    rf = receptive_field(model)
    model = model.double()
    batch = synthetic_batch(model, height=H, width=W, dtype=torch.float64)
    with torch.no_grad():
        whole = model(batch)[0].numpy()
    ok = _run(model, batch, plan_tiles(H, W, receptive=rf, core=12))
    short = _run(model, batch, plan_tiles(H, W, receptive=rf - 3, core=12))
    assert _rel(ok, whole) < 1e-5
    assert _rel(short, whole) > 1e-3


def test_pooling_alignment_matters():
    """Catches tiles cut off the pooling grid: wskp_mr with cores not a multiple of 4 must seam."""
    from mcdenoise.infer.receptive import _all_paths_open

    model = build_model("wskp_mr", "small").eval()
    _all_paths_open(model)  # random signed weights can switch the coarse levels off (then nothing seams)
    rf = receptive_field(model) + 8
    # float64: in float32 the aligned error was 1.7e-4 on an Intel Xeon and below 1e-4 on an AMD
    # EPYC (CPU-dependent conv kernels over large positive sums); 3.8e-8 in float64, 0.457 if broken.
    model = model.double()
    h, w = 2 * H, 2 * W  # room for several tiles with a 30 px overlap
    batch = synthetic_batch(model, height=h, width=w, dtype=torch.float64)
    with torch.no_grad():
        whole = model(batch)[0].numpy()
    assert len(plan_tiles(h, w, receptive=rf, align=1, core=13)) >= 4
    aligned = _run(model, batch, plan_tiles(h, w, receptive=rf, align=4, core=12))
    assert _rel(aligned, whole) < 1e-4  # the tolerance; positive weights make large sums
    misaligned = _run(model, batch, plan_tiles(h, w, receptive=rf, align=1, core=13))
    assert _rel(misaligned, whole) > 1e-3


def test_thin_probe_matches_full_model():
    """Catches the width-shrunk probe changing the geometry it is meant to keep."""
    model = build_model("layer_optimized", "small")
    assert measure_receptive_field(model, thin=True) == measure_receptive_field(model, thin=False)


def test_cores_partition_the_image():
    """Catches tiles that skip or double-write pixels at the right/bottom edges."""
    plan = plan_tiles(101, 67, receptive=9, align=4, core=30)
    cover = np.zeros((101, 67), int)
    for t in plan.tiles():
        y, x, h, w = t.core
        cover[y : y + h, x : x + w] += 1
        wy, wx, wh, ww = t.window
        assert wy % 4 == 0 and wx % 4 == 0
        assert wy <= y and wx <= x and wy + wh >= y + h and wx + ww >= x + w
    assert (cover == 1).all()
    assert plan.core == 32 and plan.overlap == 12


def test_budget_sets_the_tile_size():
    """Catches a budget that is ignored: a window must fit max_window_pixels, one tile when all fits."""
    assert len(plan_tiles(500, 400, receptive=10, max_window_pixels=500 * 400)) == 1
    plan = plan_tiles(500, 400, receptive=10, align=4, max_window_pixels=100 * 100)
    assert plan.window ** 2 <= 100 * 100 and len(plan) > 1


def test_receptive_field_does_not_depend_on_the_global_rng():
    """Catches a measurement that follows random weights: with signed random weights the 3-channel
    probe of wskp_mr measured 22 px or 8 px depending on the RNG state, and 8 px of overlap seams."""
    from mcdenoise.infer.receptive import measure_receptive_field

    found = set()
    for seed in (0, 1, 2):
        torch.manual_seed(seed)
        found.add(measure_receptive_field(build_model("wskp_mr", "small")))
    assert found == {PINNED["wskp_mr"][0]}


@pytest.mark.parametrize("name", ["kpcn", "kpcn_single"])
def test_window_variance_preset_tiles_without_seams(name):
    """The ``pixel`` preset's window variances widen the receptive field by the window radius:
    catches a probe that misses it (the variances of tile-border pixels would differ)."""
    torch.manual_seed(0)
    model = build_model(name, "pixel").eval()
    rf = receptive_field(model)
    # 4 convolutions of 5x5 see 8 pixels; the features then reach 2 further (the window's radius,
    # which covers the gradients' one pixel): 10, against the small preset's 8 + 1.
    assert rf == 10 == PINNED[name][0] - 1 + model.config.variance_window // 2
    model = model.double()
    batch = synthetic_batch(model, height=H, width=W, dtype=torch.float64)
    with torch.no_grad():
        whole = model(batch)[0].numpy()
    plan = plan_tiles(H, W, receptive=rf, align=alignment(model), core=12)
    assert len(plan) >= 6
    assert _rel(_run(model, batch, plan), whole) < 1e-4


def test_two_runs_of_the_layer_network_tile_without_seams():
    """Catches a receptive field measured through one run only: a second run's context reads the
    first run's output (LayerConfig.passes), so it looks about twice as far, and tiles cut to one
    run's field would show seams."""
    torch.manual_seed(0)
    one, two = build_model("layer", "small").eval(), build_model("layer", "small", passes=2).eval()
    two.load_state_dict(one.state_dict())
    rf = receptive_field(two)
    assert rf > receptive_field(one)
    two = two.double()
    batch = synthetic_batch(two, spp=2, height=H, width=W, dtype=torch.float64)
    with torch.no_grad():
        whole = two(batch)[0].numpy()
    plan = plan_tiles(H, W, receptive=rf, align=alignment(two), core=12)
    assert len(plan) >= 4 and plan.overlap > 0
    assert _rel(_run(two, batch, plan), whole) < 1e-4
