"""Test-time self-ensemble (mcdenoise.models.symmetry, campaign 20): the 8 orientations of an
image, each output turned back, the per-pixel median kept.

For each test, the bug it would catch is in its docstring.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mcdenoise.data.symmetry import NUM_OPS, inverse_op, source_box, spatial, turned_shape
from mcdenoise.models import build_model, synthetic_batch
from mcdenoise.models.base import Denoiser
from mcdenoise.models.symmetry import median_of, self_ensemble, transform_batch, turn_tensor, untransform
from mcdenoise.train.augment import augment_arrays

OPS = list(range(NUM_OPS))


def _rng_batch(h: int = 6, w: int = 6, s: int = 3) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    r = lambda *shape: torch.rand(*shape, generator=g, dtype=torch.float64)  # noqa: E731
    return {
        "radiance": r(1, s, 3, h, w), "normal": r(1, s, 3, h, w) * 2 - 1, "subpixel": r(1, s, 2, h, w),
        "lens": r(1, s, 2, h, w) * 2 - 1, "motion": r(1, 2, h, w) * 4 - 2, "motion_variance": r(1, 2, h, w),
        "subpixel_variance": r(1, 2, h, w), "scene_features": r(1, 5),
    }


@pytest.mark.parametrize("op", OPS)
def test_batch_turns_as_training_augmentation_does(op: int) -> None:
    """Catches inference turning an image differently from the crops the networks were trained on
    (a rotation the other way, a film vector not turned, subpixel turned about 0 instead of the
    pixel centre, a variance given M instead of M*M): augment_arrays is tested against a ray tracer."""
    batch = _rng_batch()
    got = transform_batch(batch, op)
    want = augment_arrays({k: v[0].numpy() for k, v in batch.items() if k != "scene_features"}, op)
    for name, arr in want.items():
        np.testing.assert_allclose(got[name][0].numpy(), arr, rtol=0, atol=1e-15, err_msg=name)
    assert got["scene_features"] is batch["scene_features"]


@pytest.mark.parametrize("op", OPS)
def test_turning_back_restores_a_non_square_image(op: int) -> None:
    """Catches a wrong inverse (a mirror undone by a turn, k turns undone by k more) and a quarter
    turn refused or mangled on a non-square image."""
    x = np.arange(2 * 5 * 7, dtype=np.float32).reshape(2, 5, 7)
    t = turn_tensor(torch.from_numpy(x), op).numpy()
    assert t.shape[-2:] == turned_shape(5, 7, op)
    np.testing.assert_array_equal(t, spatial(x, op, square=False))
    np.testing.assert_array_equal(untransform(t, op), x)
    assert spatial(spatial(x, op, square=False), inverse_op(op), square=False).tobytes() == x.tobytes()


@pytest.mark.parametrize("op", OPS)
def test_source_box_is_where_the_turned_box_comes_from(op: int) -> None:
    """Catches tiles of a turned image read from the wrong part of the original (seams or swapped
    tiles in a tiled self-ensemble): every box of a small non-square image is checked."""
    h, w = 4, 6
    img = np.arange(h * w).reshape(h, w)
    turned = spatial(img, op, square=False)
    th, tw = turned.shape
    for y0 in range(th):
        for x0 in range(tw):
            for bh in range(1, th - y0 + 1):
                for bw in range(1, tw - x0 + 1):
                    sy, sx, sh, sw = source_box((y0, x0, bh, bw), op, h, w)
                    np.testing.assert_array_equal(spatial(img[sy:sy + sh, sx:sx + sw], op, square=False),
                                                  turned[y0:y0 + bh, x0:x0 + bw])


def test_median_drops_one_exploded_orientation() -> None:
    """Catches the mean (or a lower median) in place of the median: one orientation's exploded
    highlight must not reach the output, and an even count gives the mean of the middle two."""
    a = np.full((3, 4, 4), 0.25, np.float32)
    outs = [a.copy() for _ in range(7)] + [np.full_like(a, 1e6)]
    assert np.array_equal(median_of(outs), a) and median_of(outs).dtype == np.float32
    vals = [np.full((1, 1, 1), v, np.float64) for v in (5.0, 1.0, 4.0, 2.0, 8.0, 3.0, 7.0, 6.0)]
    assert median_of(vals).item() == 4.5


class _Equivariant(Denoiser):
    """A sample model whose output turns with its input exactly when the film vectors are turned
    right: |lens| and the distance of subpixel from the pixel centre do not change under D4."""

    input_kind = "samples"

    def required_channels(self) -> list[str]:
        return ["radiance", "lens", "subpixel"]

    def forward(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        lens = (batch["lens"] ** 2).sum(2, keepdim=True)
        sub = ((batch["subpixel"] - 0.5) ** 2).sum(2, keepdim=True)
        blur = torch.nn.functional.avg_pool2d(batch["radiance"].mean(1), 3, 1, 1, count_include_pad=False)
        return blur * (1 + lens.mean(1) + sub.mean(1))


def test_an_equivariant_model_is_unchanged() -> None:
    """Catches outputs not turned back (or turned back the wrong way) and film vectors turned wrong:
    for a model that commutes with every turn, each orientation gives the single pass's output."""
    model = _Equivariant(None)
    batch = _rng_batch(5, 7)
    with torch.no_grad():
        one = model(batch)[0].numpy()
        for op in OPS:
            np.testing.assert_allclose(untransform(model(transform_batch(batch, op))[0].numpy(), op), one,
                                       rtol=1e-12, atol=0, err_msg=f"op {op}")
        both = self_ensemble(lambda b: model(b)[0].numpy(), batch)
    np.testing.assert_allclose(both, one, rtol=1e-12, atol=0)


def _inputs(model: Denoiser, h: int, w: int):
    from mcdenoise.infer.sources import from_arrays

    batch = synthetic_batch(model, spp=2, height=h, width=w, generator=torch.Generator().manual_seed(1))
    samples = {k: v[0].numpy() for k, v in batch.items() if k != "scene_features"}
    return from_arrays(samples["radiance"].mean(0), samples=samples,
                       scene_features=batch["scene_features"][0].numpy())


def test_tiled_self_ensemble_equals_whole_image_and_differs_from_one_pass() -> None:
    """Catches a tiled self-ensemble that seams (a turned tile read from the wrong box, a pooling
    grid shifted in a turned frame), and a flag that silently runs one pass. A non-square image
    with partial tiles; a trained-like layer model with random weights is not equivariant, so the
    ensemble must differ from its single pass."""
    from mcdenoise.infer.run import denoise_inputs

    torch.manual_seed(0)
    model = build_model("layer", "small").eval()
    inp = _inputs(model, 29, 35)
    whole, info = denoise_inputs(inp, model, device="cpu", tile=None, progress=False, self_ensemble=True)
    tiled, info_t = denoise_inputs(inp, model, device="cpu", tile=12, progress=False, self_ensemble=True)
    single, info_1 = denoise_inputs(inp, model, device="cpu", tile=None, progress=False)
    assert (info.orientations, info_t.orientations, info_1.orientations) == (8, 8, 1)
    assert len(info_t.plan) > 1
    scale = np.abs(whole).max()
    # float32 rounding of different tile sizes: measured at 5e-8 of the image's maximum (AMD EPYC,
    # tiles of 8, 12, 16); 1e-4 as test_tiling. One pass differs from the ensemble by 2x the maximum.
    assert np.abs(tiled - whole).max() / scale < 1e-4
    assert np.abs(single - whole).max() / scale > 1e-3
    assert np.isfinite(whole).all() and whole.shape == (3, 29, 35)


def test_eval_lists_a_self_ensemble_beside_each_model() -> None:
    """Catches --self-ensemble replacing the single pass (the report must compare both) or running
    unlabelled."""
    from mcdenoise.eval.lineup import build_methods

    methods = build_methods(["layer"], [], False, torch.device("cpu"), self_ensemble=True)
    labels = [m.name for m in methods]
    assert labels == ["noisy", "layer", "layer+se"]
    assert [getattr(m, "self_ensemble", None) for m in methods[1:]] == [False, True]
    assert methods[2].info["self_ensemble"] is True
