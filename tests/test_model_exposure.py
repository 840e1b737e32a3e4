"""Autoexposure (``KPCNConfig.autoexposure``, ``WSKPConfig.autoexposure``,
:mod:`mcdenoise.models.exposure`): the model is exactly
exposure-equivariant, its training losses do not depend on exposure, and tiles use the whole
image's scale."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from mcdenoise.infer.receptive import alignment, receptive_field
from mcdenoise.infer.sources import from_arrays
from mcdenoise.infer.run import denoise_inputs
from mcdenoise.models import build_model, synthetic_batch
from mcdenoise.models.exposure import EXPOSURE_SCALE, autoexposure_scale, scale_batch

KEY = 0.18


#: (model, preset) pairs that take ``autoexposure``.
MODELS = [("kpcn", "small"), ("kpcn", "pixel"), ("wskp", "small"), ("sbmc", "small"), ("layer", "small")]


def bright_half_inputs(h: int, w: int) -> tuple:
    """Pixel inputs ``(colour, albedo, normal, depth, {diffuse, specular})`` whose right half is 30x
    brighter: each tile's own autoexposure scale would differ a lot from the whole image's."""
    rng = np.random.default_rng(0)
    colour = rng.random((3, h, w), dtype=np.float32) * 0.2
    colour[:, :, w // 2 :] *= 30
    albedo = np.full((3, h, w), 0.5, np.float32)
    normal = np.zeros((3, h, w), np.float32)
    normal[2] = 1
    depth = np.ones((1, h, w), np.float32) * 2
    return colour, albedo, normal, depth, {"diffuse": colour * 0.7, "specular": colour * 0.3}


def assert_tiles_match_whole(model: torch.nn.Module, h: int, w: int) -> tuple:
    """Denoise :func:`bright_half_inputs` whole and in 16-px tiles; assert the two agree (1e-4 of
    the image maximum) and that tiling did cut the image. Returns the inputs."""
    inputs = bright_half_inputs(h, w)
    colour, albedo, normal, depth, feats = inputs

    def run(tile):
        inp = from_arrays(colour, albedo=albedo, normal=normal, depth=depth, features=feats)
        return denoise_inputs(inp, model, device="cpu", tile=tile, progress=False)

    whole, info_whole = run(None)
    tiled, info = run(16)
    assert len(info.plan) > 1 and len(info_whole.plan) == 1
    assert np.abs(tiled - whole).max() / np.abs(whole).max() < 1e-4
    return inputs


def _model(preset: str, key: float | None, seed: int = 0, name: str = "kpcn") -> torch.nn.Module:
    torch.manual_seed(seed)
    m = build_model(name, preset, autoexposure=key).eval()
    return m.double()


def _scaled(batch: dict[str, torch.Tensor], k: float) -> dict[str, torch.Tensor]:
    return scale_batch(batch, torch.full((next(iter(batch.values())).shape[0],), k, dtype=torch.float64))


def test_scale_is_key_over_the_geometric_mean_of_lit_blocks() -> None:
    """Catches an arithmetic mean (one bright lamp would set the exposure), dark blocks counted
    (a night sky would make the picture look dim), and a black image divided by zero."""
    img = torch.zeros(2, 3, 16, 16, dtype=torch.float64)
    img[0, :, :8, :8] = 4.0  # one lit block of luminance 4 ...
    img[0, :, 8:, 8:] = 0.25  # ... and one of 0.25; the other two are black
    s = autoexposure_scale(img, KEY)
    assert s[0].item() == pytest.approx(KEY / 1.0, rel=1e-6)  # sqrt(4 * 0.25) = 1
    assert s[1].item() == 1.0  # nothing lit: left as it is
    samples = img[:, None].expand(2, 4, 3, 16, 16)
    torch.testing.assert_close(autoexposure_scale(samples, KEY), s)


@pytest.mark.parametrize("name,preset", MODELS)
def test_output_follows_exposure_exactly(name: str, preset: str) -> None:
    """Catches a radiance-like input left unscaled, a variance scaled by k instead of k**2, and an
    output not divided back: any of them breaks equivariance. The same model without
    autoexposure is far from equivariant on the same batch, so the check can fail."""
    torch.manual_seed(3)
    for key, must_hold in ((KEY, True), (None, False)):
        model = _model(preset, key, name=name)
        b = synthetic_batch(model, batch=2, height=18, width=20, dtype=torch.float64)
        with torch.no_grad():
            base = model(b)
            for k in (0.01, 37.0):
                out = model(_scaled(b, k))
                err = ((out - k * base).abs().max() / (k * base).abs().max()).item()
                if must_hold:
                    assert err < 1e-9, (preset, k, err)
                else:
                    assert err > 1e-3, (preset, k, err)


def test_branch_loss_does_not_depend_on_exposure() -> None:
    """The per-branch pre-training compares forward_branches with branch_targets: catches targets
    left at the rendered exposure while the branches see the scaled image (the loss would then
    teach the network to change brightness)."""
    model = _model("small", KEY)
    b = synthetic_batch(model, batch=2, height=16, width=16, dtype=torch.float64)
    ref = {n: b[n].clone() * 0.9 for n in ("diffuse", "specular")}
    with torch.no_grad():
        def loss(batch, reference):
            out, tgt = model.forward_branches(batch), model.branch_targets(reference, batch)
            return sum(float((out[n] - tgt[n]).abs().mean()) for n in out)

        base = loss(b, ref)
        for k in (0.05, 20.0):
            assert loss(_scaled(b, k), _scaled(ref, k)) == pytest.approx(base, rel=1e-9)


@pytest.mark.parametrize("name,preset", [("kpcn", "pixel"), ("wskp", "small")])
def test_tiles_use_the_whole_image_scale(name: str, preset: str) -> None:
    """Catches tiled inference that lets each tile measure its own exposure: a dark tile next to a
    bright one would be filtered at another brightness and leave a seam."""
    model = _model(preset, KEY, name=name).float()
    colour, _, _, _, feats = assert_tiles_match_whole(model, 40, 44)
    # And the scale is the model's own measure of the whole image.
    batch = {n: torch.from_numpy(a)[None] for n, a in (("diffuse", feats["diffuse"]), ("specular", feats["specular"]),
                                                        ("radiance", colour))}
    assert model.exposure_of(batch).item() == pytest.approx(autoexposure_scale(torch.from_numpy(colour)[None], KEY).item(),
                                                            rel=1e-5)


def assert_sample_tiles_match_whole(model: torch.nn.Module, spp: int) -> None:
    """Denoise a 64x72 per-sample image with a 40x brighter right side whole and in 16-px tiles
    with the sample ``model``; assert the two agree (1e-4 of the image maximum) and that tiling
    did cut the image."""
    b = synthetic_batch(model, batch=1, spp=spp, height=64, width=72)
    b["radiance"][..., 36:] *= 40  # a bright right side
    samples = {k: v[0].numpy() for k, v in b.items() if k != "scene_features"}

    def run(tile):
        inp = from_arrays(samples["radiance"].mean(axis=0), samples=samples, scene_features=b["scene_features"][0].numpy())
        return denoise_inputs(inp, model, device="cpu", tile=tile, progress=False)

    whole, info_whole = run(None)
    tiled, info = run(16)
    assert len(info.plan) > 1 and len(info_whole.plan) == 1
    assert np.abs(tiled - whole).max() / np.abs(whole).max() < 1e-4


def test_sample_model_tiles_use_the_whole_image_scale() -> None:
    """The same for a sample model (the driver measures its scale on the pixel means)."""
    torch.manual_seed(0)
    model = build_model("layer", "small", autoexposure=KEY).eval()  # receptive field 19: windows < image
    assert_sample_tiles_match_whole(model, spp=2)


def test_given_scale_overrides_the_measured_one() -> None:
    """Catches a model that ignores ``batch["exposure_scale"]`` (tiles would measure their own)."""
    model = _model("pixel", KEY)
    b = synthetic_batch(model, batch=1, height=16, width=16, dtype=torch.float64)
    with torch.no_grad():
        own = model(b)
        given = model({**b, EXPOSURE_SCALE: model.exposure_of(b)})
        other = model({**b, EXPOSURE_SCALE: model.exposure_of(b) * 7})
    torch.testing.assert_close(given, own)
    assert (other - own).abs().max() > 1e-6


@pytest.mark.parametrize("name,preset", MODELS)
def test_autoexposure_is_saved_with_the_model_config(name: str, preset: str) -> None:
    """Catches the key lost from the config (a shipped file would load without autoexposure)."""
    model = build_model(name, preset, autoexposure=KEY)
    assert dataclasses.asdict(model.config)["autoexposure"] == KEY
    with pytest.raises(ValueError, match="autoexposure"):
        build_model(name, preset, autoexposure=0.0)
