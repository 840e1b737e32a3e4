"""Highlights: no model may invent radiance around emitter-like pixels (issue 21).

Cycles writes a light's emission colour into its albedo pass where the light is seen directly or
in a mirror (up to 1651) and the sky colour on background pixels (up to 20), with normal 0. A
model that divides by that albedo and multiplies the filtered neighbourhood back turned a 1-2 px
reflection of a point light into a 7x7 block of 10^5. The rule that fixes it is in
:mod:`mcdenoise.models.emitters`; these tests hold every registered model to it.
"""

from __future__ import annotations

import math

import numpy as np

import pytest
import torch
import torch.nn.functional as F

from mcdenoise.data.channels import base_name, is_variance_name
from mcdenoise.infer.receptive import receptive_field
from mcdenoise.models import emitters
from mcdenoise.models.emitters import ALBEDO_CHANNELS, as_reflectance, emitter_mask
from mcdenoise.models.registry import build_model, list_models, synthetic_batch
from mcdenoise.models.weights import shipped

SIZE = 40
#: An output pixel may exceed the largest input radiance within the model's receptive field by
#: at most this factor.
FACTOR = 2.0
#: Emitter pixels: (row, col, albedo, radiance). A dim emitter with a huge albedo beside a bright
#: one with a small albedo (an edge pixel of a light), a lone sky-like pixel, a 2x2 light.
EMITTERS = [
    (10, 10, 1000.0, 100.0), (10, 11, 1.5, 1e4), (11, 10, 300.0, 300.0),
    (28, 30, 20.0, 150.0),
    (30, 8, 1000.0, 1e4), (30, 9, 1000.0, 1e4), (31, 8, 1000.0, 1e4), (31, 9, 1000.0, 1e4),
]

ALL = [e.name for e in list_models()]


#: Every registered model at its small preset with random weights, kpcn's pixel preset (window
#: variances read the emitter pixels too), the combiner's own kernel (a gather over demodulated
#: colour, which an emitter's albedo would skew), and every shipped file at its own preset (ens, pixel).
CASES = ([f"{n}:small:random" for n in ALL] + ["kpcn:pixel:random", "combine:own:random"]
         + [f"{s.name}:{s.preset}:shipped" for s in shipped()])


def _model(case: str) -> torch.nn.Module:
    name, preset, weights = case.split(":")
    torch.manual_seed(0)
    model = build_model(name, preset, weights="shipped" if weights == "shipped" else None)
    return model.eval()


def surface_batch(model: torch.nn.Module, *, spp: int = 4, size: int = SIZE, seed: int = 1) -> dict[str, torch.Tensor]:
    """Plausible surfaces only (albedo in [0, 1], unit normals): radiance = albedo x a smooth
    irradiance x heavy-tailed noise, plus a small specular part, per sample for sample models."""
    g = torch.Generator().manual_seed(seed)
    batch = synthetic_batch(model, spp=spp, height=size, width=size, generator=g)
    rad = batch.get("radiance", batch.get("diffuse"))
    assert rad is not None
    shape = rad.shape
    yy, xx = torch.meshgrid(torch.linspace(0, 3, size), torch.linspace(0, 3, size), indexing="ij")
    irradiance = 1.0 + 0.6 * torch.sin(yy * 2.1) * torch.cos(xx * 1.7)
    noise = 1.0 / (1.0 - 0.9 * torch.rand(shape, generator=g))
    albedo = next((batch[n] for n in ALBEDO_CHANNELS if n in batch), None)
    a = albedo if albedo is not None else torch.full(shape, 0.5)
    diffuse = a * irradiance * noise
    specular = 0.1 * irradiance * torch.rand(shape, generator=g)
    for name in list(batch):
        if name == "scene_features" or is_variance_name(name):
            continue
        base = base_name(name)
        if base == "diffuse":
            batch[name] = diffuse
        elif base == "specular":
            batch[name] = specular
        elif base == "radiance":
            batch[name] = diffuse + specular
    if "oidn" in batch:  # the combiner's other candidate: a candidate image, here the noisy mean
        batch["oidn"] = batch["radiance"].clone()
    return batch


def emitter_batch(model: torch.nn.Module, **kw: object) -> dict[str, torch.Tensor]:
    """:func:`surface_batch` with the :data:`EMITTERS` written as Cycles writes them: albedo above
    1 (the emission colour), normal 0, radiance 100-10^4, in every sample."""
    batch = surface_batch(model, **kw)  # type: ignore[arg-type]
    for y, x, alb, rad in EMITTERS:
        for name in list(batch):
            if name == "scene_features" or is_variance_name(name):
                continue
            base = base_name(name)
            px = batch[name][..., y, x]
            if base.startswith("albedo"):
                px[...] = alb
            elif base.startswith("normal"):
                px[...] = 0.0
            elif base in ("radiance", "oidn"):
                px[...] = rad
            elif base in ("diffuse", "specular"):
                px[...] = rad / 2
    return batch


def _input_radiance(batch: dict[str, torch.Tensor]) -> torch.Tensor:
    """(B, H, W): the largest input radiance value of each pixel (any channel, any sample, any
    candidate the model mixes)."""
    parts = []
    if "radiance" in batch:
        parts.append(batch["radiance"])
    else:
        parts.append(batch["diffuse"] + batch["specular"])
    if "oidn" in batch:
        parts.append(batch["oidn"])
    m = None
    for p in parts:
        v = p.amax(dim=(1, 2)) if p.dim() == 5 else p.amax(dim=1)
        m = v if m is None else torch.maximum(m, v)
    return m


def _neighbourhood_max(x: torch.Tensor, radius: int) -> torch.Tensor:
    r = min(radius, x.shape[-1] - 1, x.shape[-2] - 1)
    return F.max_pool2d(x.unsqueeze(1), 2 * r + 1, stride=1, padding=r).squeeze(1)


@pytest.mark.parametrize("case", CASES)
def test_no_output_exceeds_its_input_neighbourhood(case: str) -> None:
    """Catches issue 21's exploding highlights: wskp (and wskp_mr, kpcn's diffuse branch) divided
    the radiance by an emitter's albedo (up to 10^3) and multiplied the filtered neighbourhood back
    by it, so a pixel came out far above every input radiance it can see. Every registered model,
    random and shipped weights: no output pixel above FACTOR x the largest input radiance within
    its receptive field. (dpcn predicts colours directly, so for it the bound holds by its emitter
    pixels passing through and by this test, not by construction.)"""
    model = _model(case)
    name, weights = case.split(":")[0], case
    batch = emitter_batch(model)
    with torch.no_grad():
        out = model(batch)
    assert torch.isfinite(out).all(), f"{name} ({weights}): non-finite output"
    bound = FACTOR * _neighbourhood_max(_input_radiance(batch), receptive_field(model))
    peak = out.amax(dim=1)
    over = peak > bound
    if over.any():
        ratio = (peak / bound * FACTOR)[over].max().item()
        ys, xs = torch.nonzero(over[0], as_tuple=True)
        pytest.fail(f"{name} ({weights}): {int(over.sum())} pixels above {FACTOR}x their input neighbourhood's "
                    f"maximum, worst {ratio:.3g}x, e.g. at (y={int(ys[0])}, x={int(xs[0])})")


@pytest.mark.parametrize("case", CASES)
def test_lights_do_not_bleed_into_their_neighbours(case: str) -> None:
    """Catches the halo around a light: its 10^4 spread into the surfaces around it by their
    kernels (shipped wskp, kpcn and layer put 260-1600 on surfaces of about 1). Every output pixel
    that is not an emitter stays within FACTOR x the largest input radiance of the pixels that are
    not emitters within its receptive field. Not combine: its candidates are OIDN's output and the
    noisy mean, both with the light in them, and its bound is over those (docs/models/combine.md)."""
    name, weights = case.split(":")[0], case
    if name == "combine":
        pytest.skip("combine mixes OIDN's output and the noisy mean, lights included (module docstring)")
    model = _model(case)
    batch = emitter_batch(model)
    with torch.no_grad():
        out = model(batch)
    lights = torch.zeros((1, SIZE, SIZE), dtype=torch.bool)
    for y, x, _, _ in EMITTERS:
        lights[:, y, x] = True
    surfaces = _input_radiance(batch).masked_fill(lights, 0.0)
    bound = FACTOR * _neighbourhood_max(surfaces, receptive_field(model))
    over = (out.amax(dim=1) > bound) & ~lights
    if over.any():
        ratio = (out.amax(dim=1) / bound * FACTOR)[over].max().item()
        pytest.fail(f"{name} ({weights}): {int(over.sum())} surface pixels above {FACTOR}x the surfaces around "
                    f"them, worst {ratio:.3g}x: the lights bleed into them")


@pytest.mark.parametrize("case", CASES)
def test_emitter_pixels_pass_through(case: str) -> None:
    """Catches an emitter pixel that is still filtered (blurred into, or darkened by, its
    neighbours): every model that reads an albedo returns the input radiance there."""
    model = _model(case)
    name, weights = case.split(":")[0], case
    if name == "combine":  # its own kernel divides, but by as_reflectance's albedo (1 at emitters)
        pytest.skip("combine's output is a convex combination of its candidates at every pixel, emitters included")
    if not any(n in model.required_channels() for n in ALBEDO_CHANNELS):
        pytest.skip(f"{name} reads no albedo it divides by")
    batch = emitter_batch(model)
    with torch.no_grad():
        out = model(batch)
    rad = batch["radiance"] if "radiance" in batch else batch["diffuse"] + batch["specular"]
    if rad.dim() == 5:
        rad = rad.mean(dim=1)
    for y, x, _, _ in EMITTERS:
        torch.testing.assert_close(out[..., y, x], rad[..., y, x], rtol=1e-6, atol=0,
                                   msg=lambda m, y=y, x=x: f"{name} ({weights}) at ({y}, {x}): {m}")


def _unguarded(monkeypatch: pytest.MonkeyPatch) -> None:
    """Switch the emitter rule off in every model module (the code before issue 21)."""
    import mcdenoise.models.kpcn as kpcn
    import mcdenoise.models.layer as layer
    import mcdenoise.models.sbmc as sbmc
    import mcdenoise.models.wskp as wskp
    import mcdenoise.models.wskp_mr as wskp_mr

    for mod in (kpcn, layer, sbmc, wskp, wskp_mr):
        if hasattr(mod, "as_reflectance"):
            monkeypatch.setattr(mod, "as_reflectance", lambda a: a)
        monkeypatch.setattr(mod, "pass_through", lambda out, radiance, mask: out)


@pytest.mark.parametrize("case", CASES)
def test_rule_is_the_identity_without_emitters(case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches a fix that moves the numbers of inputs in our own convention (albedo in [0, 1],
    0 on a miss, as every procedural dataset is): with every albedo <= 1 (some exactly 0 and 1,
    some pixels with normal 0) the output is bit-identical to the model without the rule, shipped
    weights included, in training mode (gradients on) and at inference."""
    model = _model(case)
    name, weights = case.split(":")[0], case
    batch = surface_batch(model, seed=4)
    for n in ALBEDO_CHANNELS:
        if n in batch:
            a = batch[n]
            a[..., 0, :] = 1.0
            a[..., 1, :] = 0.0
    for n in ("normal", "normal_diffuse"):
        if n in batch:
            batch[n][..., 2, 3:7] = 0.0
    with torch.no_grad():
        guarded = model(batch)
    guarded_grad = model(batch).detach()
    _unguarded(monkeypatch)
    with torch.no_grad():
        plain = model(batch)
    plain_grad = model(batch).detach()
    assert torch.equal(guarded, plain), f"{name} ({weights}): the emitter rule changed an albedo <= 1 input"
    assert torch.equal(guarded_grad, plain_grad), f"{name} ({weights}): the rule changed the training forward"


def test_emitter_mask_and_reflectance() -> None:
    """The rule's two functions: any channel (any sample) above 1 marks the pixel; its albedo
    reads 1 in every channel and sample; other pixels keep their values bit for bit."""
    a = torch.rand(1, 3, 4, 5)
    a[0, 1, 2, 3] = 1.0 + 1e-6
    a[0, :, 0, 0] = 1.0  # exactly 1: a white surface, not an emitter
    m = emitter_mask(a)
    assert m.shape == (1, 1, 4, 5) and m.sum() == 1 and m[0, 0, 2, 3]
    r = as_reflectance(a)
    assert torch.equal(r[0, :, 2, 3], torch.ones(3))
    keep = ~m.expand_as(a)
    assert torch.equal(r[keep], a[keep])
    s = torch.rand(1, 4, 3, 4, 5)
    s[0, 2, 0, 1, 1] = 50.0
    ms = emitter_mask(s)
    assert ms.shape == (1, 1, 4, 5) and ms.sum() == 1 and ms[0, 0, 1, 1]
    assert torch.equal(as_reflectance(s)[0, :, :, 1, 1], torch.ones(4, 3))
    with pytest.raises(ValueError, match="emitter_mask"):
        emitter_mask(torch.rand(3, 4))
    assert emitters.pass_through(a, a, None) is a
    assert math.isfinite(float(as_reflectance(torch.full((1, 3, 1, 1), 1e30)).max()))


def test_fill_from_neighbours() -> None:
    """The fill: a lone pixel becomes the mean of its 8 neighbours, a block is filled inward from
    its border, other pixels keep their values bit for bit, per-sample buffers per sample, and a
    batch without emitters is returned as it is."""
    x = torch.rand(1, 3, 9, 9)
    mask = torch.zeros(1, 1, 9, 9, dtype=torch.bool)
    mask[0, 0, 1, 1] = True
    mask[0, 0, 4:8, 4:8] = True
    x[0, :, 1, 1] = 1e4
    x[0, :, 4:8, 4:8] = 1e4
    got = emitters.fill_from_neighbours(x, mask)
    ring = torch.cat([x[0, :, 0:3, 0:3].reshape(3, -1)[:, :4], x[0, :, 0:3, 0:3].reshape(3, -1)[:, 5:]], dim=1)
    torch.testing.assert_close(got[0, :, 1, 1], ring.mean(dim=1))
    assert torch.equal(got[~mask.expand_as(x)], x[~mask.expand_as(x)])
    assert got.max() <= x[~mask.expand_as(x)].max()
    s = torch.rand(1, 2, 3, 9, 9)
    s[:, :, :, 4:8, 4:8] = 1e4
    gs = emitters.fill_from_neighbours(s, mask)
    for i in range(2):
        assert torch.equal(gs[:, i], emitters.fill_from_neighbours(s[:, i], mask))
    batch = {"radiance": x}
    assert emitters.fill_emitters(batch, torch.zeros_like(mask)) is batch


@pytest.mark.parametrize("name", ["wskp", "wskp_mr"])
def test_tiles_match_the_whole_image_around_lights(name: str) -> None:
    """Catches seams at lights in tiled denoising: the fill reads up to FILL_STEPS pixels, beyond
    the receptive field that sizes the tile overlap. A band of light (rows 4-15) is filled from
    above in its upper half, which a tile whose window starts inside the band cannot see; the tiled
    output must equal the whole image's (the overlap grows by the fill's reach)."""
    from mcdenoise.infer.run import denoise_inputs
    from mcdenoise.infer.sources import from_arrays

    model = _model(f"{name}:small:random")
    batch = emitter_batch(model, size=64)
    for n, v in ((n, v) for n, v in batch.items() if n != "scene_features"):
        block = v[..., 4:16, :]
        if n == "albedo":
            block[...] = 500.0
        elif n == "normal":
            block[...] = 0.0
        elif n == "radiance":
            block[...] = 3000.0
    with torch.no_grad():
        whole = model(batch)[0].numpy()
    inputs = from_arrays(batch["radiance"][0].numpy(), albedo=batch["albedo"][0].numpy(),
                         normal=batch["normal"][0].numpy(), depth=batch["depth"][0].numpy())
    tiled, run = denoise_inputs(inputs, model, device="cpu", tile=16, progress=False)
    assert len(run.plan) > 1
    np.testing.assert_allclose(tiled, whole, rtol=1e-4, atol=1e-5)


def test_overlap_grows_only_for_images_with_emitters() -> None:
    """Catches the fill's extra tile overlap applied to every image (more work on all of ours,
    which have no albedo above 1) or to none (seams at lights)."""
    from mcdenoise.infer.run import emitter_reach
    from mcdenoise.infer.sources import from_arrays

    colour = np.ones((3, 8, 8), np.float32)
    albedo = np.full((3, 8, 8), 1.0, np.float32)
    assert emitter_reach(from_arrays(colour, albedo=albedo), ["radiance", "albedo"]) == 0
    albedo[1, 2, 3] = 1.5
    assert emitter_reach(from_arrays(colour, albedo=albedo), ["radiance", "albedo"]) == emitters.FILL_STEPS + 1
    assert emitter_reach(from_arrays(colour, albedo=albedo), ["radiance"]) == 0  # a model that reads no albedo
