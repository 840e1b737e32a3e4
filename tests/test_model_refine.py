"""The second stage over a frozen model (``refine``, campaign 29): its op against a reference,
its guarantees, the frozen base and the start from shipped weights."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from mcdenoise.models import build_model, synthetic_batch
from mcdenoise.models.combine import apply_weights
from mcdenoise.models.refine import GLOW_RADII, NEAR_RADII, blur, context_features, noisy_band, power_mean

ROOT = Path(__file__).resolve().parents[1]


def _reference_taps(candidates: list[torch.Tensor], dilations: list[int], weights: torch.Tensor, k: int) -> torch.Tensor:
    """The sum written out: one shifted, edge-clamped copy of each candidate per tap."""
    b, _, h, w = candidates[0].shape
    r = k // 2
    out = torch.zeros_like(candidates[0])
    ys = torch.arange(h).view(h, 1)
    xs = torch.arange(w).view(1, w)
    for c, (img, d) in enumerate(zip(candidates, dilations)):
        for t, (dy, dx) in enumerate((dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)):
            yy = (ys + dy * d).clamp(0, h - 1).expand(h, w)
            xx = (xs + dx * d).clamp(0, w - 1).expand(h, w)
            out = out + img[:, :, yy, xx] * weights[:, c * k * k + t].unsqueeze(1)
    return out


def _random_weights(n: int, k: int, h: int, w: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.softmax(torch.randn(1, n * k * k, h, w, generator=g, dtype=torch.float64) * 2, dim=1)


def test_dilated_taps_equals_the_written_out_sum_float64() -> None:
    """Catches a tap order that differs from the weights' (unfold's row-major order), a dilation
    that is not applied to a candidate or applied to the wrong one, and zero padding at borders
    (the edge must repeat: a dark rim would pull border pixels down)."""
    g = torch.Generator().manual_seed(0)
    cands = [torch.rand(1, 3, 13, 17, generator=g, dtype=torch.float64) for _ in range(3)]
    dil = [1, 2, 4]
    w = _random_weights(3, 5, 13, 17, 1)
    torch.testing.assert_close(apply_weights(cands, w, 5, dil), _reference_taps(cands, dil, w, 5), rtol=1e-12, atol=1e-12)


def test_dilated_taps_gradcheck() -> None:
    """Catches a backward that differs from the forward (unfold's adjoint through the dilation)."""
    g = torch.Generator().manual_seed(2)
    cands = [torch.rand(1, 3, 6, 7, generator=g, dtype=torch.float64, requires_grad=True) for _ in range(2)]
    w = _random_weights(2, 3, 6, 7, 3).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b, ww: apply_weights([a, b], ww, 3, [1, 2]), (*cands, w))


def test_constant_image_stays_constant() -> None:
    """Catches weights that are not a partition of unity, or a blur that is not normalised at the
    border (a constant image must come out the same constant, whatever the weights)."""
    c = torch.full((2, 3, 11, 9), 0.37, dtype=torch.float64)
    cands = [c, c.clone(), blur(c, 2), blur(c, 4)]
    w = _random_weights(4, 5, 11, 9, 4).expand(2, -1, -1, -1)
    torch.testing.assert_close(apply_weights(cands, w, 5, [1, 1, 2, 4]), c, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(blur(c, 4), c, rtol=1e-12, atol=1e-12)


def test_blur_commutes_with_shifts_away_from_the_border() -> None:
    """Catches a strided (block) coarse candidate: its output would depend on where a tile starts,
    so tiled and whole-image denoising would disagree."""
    x = torch.rand(1, 3, 24, 24, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    shifted = torch.roll(x, shifts=(3, 5), dims=(2, 3))
    a = torch.roll(blur(x, 4), shifts=(3, 5), dims=(2, 3))[..., 10:18, 10:18]
    b = blur(shifted, 4)[..., 10:18, 10:18]
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_noisy_band_swaps_only_the_coarse_band_float64() -> None:
    """Catches a band that is not the base's fine detail plus the noisy mean's coarse band (the sum
    written out with avg_pool), one that moves the base where the noisy mean agrees with it, a clamp
    that lets a firefly into the band, and a negative output."""
    g = torch.Generator().manual_seed(11)
    base = torch.rand(1, 3, 20, 18, dtype=torch.float64, generator=g) + 0.1
    torch.testing.assert_close(noisy_band(base, base, 4, 1.0), base, rtol=1e-12, atol=1e-12)
    noisy = base * (1 + 0.5 * torch.randn(base.shape, dtype=torch.float64, generator=g)).clamp_min(0)
    pad = lambda x: F.pad(x, (3, 3, 3, 3), mode="replicate")  # noqa: E731
    box = lambda x: F.avg_pool2d(pad(x), 7, stride=1)  # noqa: E731
    hi = F.max_pool2d(pad(base)[..., 2:-2, 2:-2], 3, 1)
    want = (base - box(base) + box(torch.minimum(noisy, 8.0 * hi))).clamp_min(0)
    torch.testing.assert_close(noisy_band(base, noisy, 4, 8.0), want, rtol=1e-12, atol=1e-12)
    fly = base.clone()
    fly[..., 10, 9] = 1e6
    assert noisy_band(base, fly, 4, 2.0).amax() <= 3 * base.amax()
    assert (noisy_band(base, torch.zeros_like(base), 4, 2.0) >= 0).all()


def test_noisy_band_leaves_bright_sparse_pixels_out_of_the_box_float64() -> None:
    """Catches the halo of a partly covered emitter: a base with one pixel 1e4 brighter than a flat
    surround, and a noisy mean that misses it (0 there) and equals the base elsewhere. Without
    ``exclude`` the box spreads the miss over the surround (darker by 1e4 / 49); with it the surround
    keeps the base. Also: with ``m`` all 1 (a flat base) it equals the plain band, and it never goes
    negative."""
    base = torch.full((1, 3, 15, 15), 0.5, dtype=torch.float64)
    base[..., 7, 7] = 1e4
    noisy = base.clone()
    noisy[..., 7, 7] = 0.0
    plain = noisy_band(base, noisy, 4, 4.0)
    kept = noisy_band(base, noisy, 4, 4.0, exclude=4.0)
    ring = torch.ones(15, 15, dtype=torch.bool)
    ring[7, 7] = False
    assert (plain[..., ring] - 0.5).abs().amax() > 0.1  # the halo: the surround goes to 0 (clamped)
    torch.testing.assert_close(kept[..., ring], base[..., ring], rtol=1e-12, atol=1e-12)
    g = torch.Generator().manual_seed(12)
    flat = torch.full((1, 3, 12, 12), 0.3, dtype=torch.float64)
    n = flat * torch.rand(flat.shape, dtype=torch.float64, generator=g) * 2
    torch.testing.assert_close(noisy_band(flat, n, 3, 8.0, exclude=2.0), noisy_band(flat, n, 3, 8.0),
                               rtol=1e-12, atol=1e-12)
    assert (noisy_band(base, torch.zeros_like(base), 4, 2.0, exclude=2.0) >= 0).all()


def _model(seed: int = 0, **over: object) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model("refine", "small", **over)


def test_starts_as_the_base() -> None:
    """Catches the identity start on the wrong tap or candidate (the centre tap of the base
    output): a fresh stage would then blur or brighten the base's output before any training."""
    model = _model().eval()
    batch = synthetic_batch(model, spp=4, height=24, width=20, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        out, base = model(batch), model.base(batch)
    err = ((out - base).abs().amax() / base.abs().amax()).item()
    assert err < 0.02, f"a fresh refine stage moves its base's output by {err:.3f} of its maximum"


def test_base_is_frozen_and_every_head_parameter_learns() -> None:
    """Catches a base that trains (its gradients or a training-mode switch) and a head parameter
    cut off from the loss."""
    model = _model().train()
    assert not model.base.training
    batch = synthetic_batch(model, spp=3, height=16, width=16, generator=torch.Generator().manual_seed(7))
    model(batch).square().mean().backward()
    assert all(p.grad is None and not p.requires_grad for p in model.base.parameters())
    missing = [n for n, p in model.net.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]
    assert not missing, f"head parameters without a gradient: {missing[:3]}"


def test_noisy_candidate_is_clamped_to_the_base_neighbourhood() -> None:
    """Catches a firefly of the few samples reaching the output through the noisy candidate: it may
    not exceed the base output's 3x3 maximum times the clamp."""
    model = _model().eval()
    base = torch.rand(1, 3, 9, 9, dtype=torch.float64)
    noisy = base.clone()
    noisy[..., 4, 4] = 1e5
    cands = model.candidates(base, noisy)
    hi = F.max_pool2d(F.pad(base, (1, 1, 1, 1), mode="replicate"), 3, 1)
    assert (cands[1] <= hi * model.config.noisy_clamp + 1e-12).all()


@pytest.mark.parametrize("context,spread", [(False, False), (True, False), (True, True)])
def test_exposure_equivariant(context: bool, spread: bool) -> None:
    """Catches features that are not exposure-normalised (log1p of raw radiance; with ``context``,
    context features taken before the exposure scale; with ``spread``, the halves' outputs left
    unscaled): the same picture ten times brighter must come out ten times brighter, filtered the
    same way."""
    model = _model(base_config={"autoexposure": 0.18}, context=context, spread=spread).eval()
    with torch.no_grad():
        for p in model.net.parameters():
            p.normal_(0, 0.3)  # away from the identity start, so the head's choices matter
    batch = synthetic_batch(model, spp=4, height=16, width=16, generator=torch.Generator().manual_seed(8))
    bright = dict(batch)
    for name in ("radiance", "specular"):
        bright[name] = batch[name] * 10
    with torch.no_grad():
        a, b = model(batch), model(bright)
    torch.testing.assert_close(b, a * 10, rtol=2e-4, atol=1e-5)


def test_init_script_puts_the_shipped_base_in(tmp_path: Path) -> None:
    """Catches a start file whose base is not the shipped weights (a random base, or the preset's
    configuration instead of the card's): its base output must equal the shipped model's."""
    from mcdenoise.models.weights import load_denoiser

    dst = tmp_path / "init.safetensors"
    subprocess.run([sys.executable, str(ROOT / "scripts" / "refine_init.py"), "layer-small", str(dst), "--preset", "small"],
                   check=True, capture_output=True, text=True, cwd=ROOT)
    model, info = load_denoiser(dst)
    shipped, _ = load_denoiser("layer-small")
    assert info["name"] == "refine"
    batch = synthetic_batch(shipped, spp=4, height=16, width=16, generator=torch.Generator().manual_seed(9))
    with torch.no_grad():
        torch.testing.assert_close(model.base(batch), shipped(batch), rtol=0, atol=0)


def _reference_power_mean(x: torch.Tensor, r: int, p: int) -> torch.Tensor:
    """The window mean written out: every pixel's (2r+1)^2 neighbours, the edge repeated."""
    h, w = x.shape[-2:]
    acc = torch.zeros_like(x)
    ys, xs = torch.arange(h).view(h, 1), torch.arange(w).view(1, w)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            acc = acc + x[..., (ys + dy).clamp(0, h - 1).expand(h, w), (xs + dx).clamp(0, w - 1).expand(h, w)] ** p
    return (acc / (2 * r + 1) ** 2) ** (1.0 / p)


def test_power_mean_equals_the_written_out_window_float64() -> None:
    """Catches zero padding at the border (a dark rim would read as 'a light nearby' on the other
    side), a window of the wrong size and a missing root."""
    x = torch.rand(2, 1, 11, 14, dtype=torch.float64, generator=torch.Generator().manual_seed(10))
    for r in (1, 4):
        torch.testing.assert_close(power_mean(x, r, 4), _reference_power_mean(x, r, 4), rtol=1e-12, atol=1e-12)


def test_context_features_gradcheck() -> None:
    """Catches a backward that differs from the forward, and a gradient that is not finite on a
    black window (the floor under the power mean's root)."""
    g = torch.Generator().manual_seed(11)
    lum = (torch.rand(1, 1, 9, 10, generator=g, dtype=torch.float64) + 0.1).requires_grad_(True)
    mask = torch.zeros(1, 1, 9, 10, dtype=torch.bool)
    mask[..., 4, 4] = True
    assert torch.autograd.gradcheck(lambda t: context_features(t, mask), (lum,))
    black = torch.zeros(1, 1, 9, 10, dtype=torch.float64, requires_grad=True)
    context_features(black, None).sum().backward()
    assert torch.isfinite(black.grad).all()


def test_context_features_locate_a_light_and_ignore_exposure() -> None:
    """Catches proximity windows of the wrong reach (a light 5 pixels away must register in the
    13x13 window and not in the 5x5), a brightness context that reads a flat wall as 'near a
    light', and one that is not exposure-invariant (log of raw luminance instead of a ratio)."""
    lum = torch.full((1, 1, 31, 31), 0.05, dtype=torch.float64)
    lum[..., 15, 15] = 500.0  # a lamp's bright pixel (as in a reflection: not in the emitter mask)
    mask = torch.zeros(1, 1, 31, 31, dtype=torch.bool)
    mask[..., 15, 20] = True
    f = context_features(lum, mask)
    near_small, near_wide, glow_small, glow_wide = f[0, :, 15]
    assert near_small[20] > 0 and near_small[15] == 0 and near_wide[15] > 0 and near_wide[13] == 0
    assert near_small[20] < 1 and NEAR_RADII == (2, 6)
    # 4 px from the bright pixel: inside the 9x9 window; 10 px: only the 25x25 one reaches it.
    assert glow_small[11] > 3 and glow_small[10] == 0 and glow_wide[5] > 3 and GLOW_RADII == (4, 12)
    flat = context_features(torch.full((1, 1, 31, 31), 0.05, dtype=torch.float64), None)
    torch.testing.assert_close(flat, torch.zeros_like(flat), rtol=0, atol=1e-12)
    # Exposure: 8x brighter, the same glow (the floor under the luminance is 1e-3: far below these).
    glow8 = context_features(lum * 8, mask)[:, 2:]
    torch.testing.assert_close(glow8, f[:, 2:], rtol=0, atol=2e-2)


@pytest.mark.parametrize("spread", [False, True])
def test_context_preset_tiles_like_the_whole_image(spread: bool) -> None:
    """Catches a receptive field measured too short for the context windows (a max pool's gradient
    reaches only its argmax, so the probe would cut tiles too tight), and context features that
    depend on where a tile starts; with ``spread``, halves of the samples that differ between a tile
    and the whole image. Tiles get the whole image's exposure scale, as denoise gives them."""
    from mcdenoise.infer.receptive import alignment, receptive_field
    from mcdenoise.infer.tiling import plan_tiles, run_tiled
    from mcdenoise.models.exposure import EXPOSURE_SCALE, batch_exposure

    model = _model(context=True, spread=spread).eval()
    with torch.no_grad():
        for p in model.net.parameters():
            p.normal_(0, 0.3)  # away from the identity start, so the features matter
    rf = receptive_field(model)
    assert rf == 43 + max(GLOW_RADII), "the context windows add their radius to the stage's reach"
    model = model.double()
    h, w = 61, 67
    batch = synthetic_batch(model, spp=2, height=h, width=w, dtype=torch.float64,
                            generator=torch.Generator().manual_seed(12))
    scale = batch_exposure(batch, model.exposure_colour(batch), model.autoexposure)

    def read(tile):
        y0, x0, th, tw = tile.window
        b = {k: (v if k == "scene_features" else v[..., y0 : y0 + th, x0 : x0 + tw]) for k, v in batch.items()}
        return {**b, EXPOSURE_SCALE: scale}

    def tiled_error(receptive: int) -> float:
        plan = plan_tiles(h, w, receptive=receptive, align=alignment(model), core=12)
        assert len(plan) >= 4
        tiled = torch.from_numpy(run_tiled(model, read, plan))
        return ((tiled - whole[0]).abs().amax() / whole.abs().amax()).item()

    with torch.no_grad():
        whole = model(batch)
        assert tiled_error(rf) < 1e-9, "tiles differ from the whole image"
        assert tiled_error(rf - max(GLOW_RADII)) > 1e-6, "the context windows' reach did not matter: the test is blind"


def _two_members() -> tuple[torch.nn.Module, torch.nn.Module]:
    """Two one-head stages over one base (same seed), their heads moved apart from the identity start."""
    a, b = _model(0).double().eval(), _model(0).double().eval()
    with torch.no_grad():
        for i, m in enumerate((a, b)):
            g = torch.Generator().manual_seed(20 + i)
            for p in m.net.parameters():
                p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 0.3)
    return a, b


def _ensemble_of(a: torch.nn.Module, b: torch.nn.Module) -> torch.nn.Module:
    ens = _model(1, heads=2).double().eval()
    state = {k: v for k, v in a.state_dict().items()}
    state.update({f"extra_heads.0.{k.removeprefix('net.')}": v for k, v in b.state_dict().items() if k.startswith("net.")})
    ens.load_state_dict(state, strict=True)
    return ens


def test_two_heads_give_the_mean_of_their_members_float64() -> None:
    """Catches an ensemble that averages logits instead of softmax weights (not the members' mean
    output, and no longer their convex combination), that reads one head twice, or that normalises by
    the wrong count: its output must be the mean of the two one-head stages' outputs."""
    a, b = _two_members()
    ens = _ensemble_of(a, b)
    batch = {k: v.double() for k, v in synthetic_batch(a, spp=4, height=16, width=16,
                                                           generator=torch.Generator().manual_seed(10)).items()}
    with torch.no_grad():
        ya, yb, ye = a(batch), b(batch), ens(batch)
    assert (ya - yb).abs().amax() > 1e-3  # the members differ, so the test can tell them apart
    torch.testing.assert_close(ye, (ya + yb) / 2, rtol=1e-10, atol=1e-12)


def test_every_head_of_an_ensemble_learns() -> None:
    """Catches an extra head left out of the forward pass (its parameters would never train)."""
    model = _model(heads=3).train()
    batch = synthetic_batch(model, spp=3, height=16, width=16, generator=torch.Generator().manual_seed(11))
    model(batch).square().mean().backward()
    for i, net in enumerate([model.net, *model.extra_heads]):
        assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in net.parameters()), f"head {i}"


def _save_refine(m: torch.nn.Module, path: Path) -> str:
    """``m`` as a one-file refine stage (preset "small" with its configuration), as training saves it."""
    import dataclasses
    import json

    from safetensors.torch import save_file

    cfg = json.loads(json.dumps(dataclasses.asdict(m.config), default=list))
    save_file({k: v.float().contiguous() for k, v in m.state_dict().items()}, str(path),
              metadata={"model": "refine", "preset": "small", "model_config": json.dumps(cfg)})
    return str(path)


def _assert_ensemble_is_the_mean(tensors: dict, meta: dict, members: tuple, path: Path, seed: int) -> None:
    """The ensemble file (``tensors``, ``meta``) saved to ``path`` loads back and gives the mean of
    ``members``' outputs on a synthetic batch."""
    from safetensors.torch import save_file

    from mcdenoise.models.weights import load_denoiser

    save_file(tensors, str(path), metadata=meta)
    ens, _ = load_denoiser(path)
    batch = synthetic_batch(ens, spp=4, height=16, width=16, generator=torch.Generator().manual_seed(seed))
    with torch.no_grad():
        want = sum(m.float()(batch) for m in members) / len(members)
        torch.testing.assert_close(ens(batch), want, rtol=1e-5, atol=1e-6)


def test_ensemble_script_joins_members_over_one_base_and_refuses_another(tmp_path: Path) -> None:
    """Catches a file whose second head is not the second member's, and an ensemble of heads trained
    over different bases (its heads would read features of a base they never saw)."""
    import json

    from safetensors import safe_open
    from safetensors.torch import save_file

    from mcdenoise.models.weights import load_denoiser
    from repo_scripts import load_script

    def save(m: torch.nn.Module, name: str) -> str:
        return _save_refine(m, tmp_path / name)

    a, b = _two_members()
    pa, pb = save(a, "a.safetensors"), save(b, "b.safetensors")
    script = load_script("refine_ensemble")
    # A member saved before the heads field existed (no "heads" in its config) is the same configuration.
    old = tmp_path / "old.safetensors"
    with safe_open(pa, "pt") as h:
        cfg = json.loads(h.metadata()["model_config"])
        tensors0 = {k: h.get_tensor(k) for k in h.keys()}
    cfg.pop("heads")
    save_file(tensors0, str(old), metadata={"model": "refine", "preset": "small", "model_config": json.dumps(cfg)})
    script.ensemble([str(old), pb], "small")
    tensors, meta = script.ensemble([pa, pb], "small")
    assert json.loads(meta["model_config"])["heads"] == 2
    _assert_ensemble_is_the_mean(tensors, meta, (a, b), tmp_path / "ens.safetensors", seed=12)
    other = _model(5).eval()  # another seed: another base
    with pytest.raises(ValueError, match="base tensor .* differs"):
        script.ensemble([pa, save(other, "c.safetensors")], "small")
    # As a run folder for the ship tool: the members' CPU seconds summed, the ensemble's config, loads back.
    runs = []
    for i, path in enumerate((pa, pb)):
        d = tmp_path / f"run{i}"
        d.mkdir()
        Path(path).rename(d / "model.safetensors")
        cfg = json.loads(meta["model_config"]) | {"heads": 1}
        (d / "config.json").write_text(json.dumps({"train": {"model": "refine", "preset": "small", "seed": i, "data": "x"},
                                                   "model_config": cfg}))
        (d / "result.json").write_text(json.dumps({"steps": 5, "wall_s": 10.0, "wall_s_this_call": 10.0,
                                                   "cpu_s_this_call": 20.0 + i, "device": "cpu"}))
        runs.append(str(d))
    script.write_run(tmp_path / "ens", runs, *script.ensemble(runs, "small"))
    assert json.loads((tmp_path / "ens" / "result.json").read_text())["cpu_s_this_call"] == 41.0
    model, info = load_denoiser(tmp_path / "ens")
    assert info["preset"] == "small" and model.config.heads == 2


def test_ensemble_script_widens_a_head_without_spread_to_what_it_computed(tmp_path: Path) -> None:
    """Catches a widened head whose zero columns sit on the wrong input channels (it would read the
    spread features as if they were its own, or shift every feature after the padding), and an
    ensemble of heads with and without spread that forms without being asked (``--widen``)."""
    import json

    from repo_scripts import load_script

    def save(m: torch.nn.Module, name: str) -> str:
        return _save_refine(m, tmp_path / name)

    plain, spread = _model(0, context=True).double().eval(), _model(0, context=True, spread=True).double().eval()
    with torch.no_grad():
        for i, m in enumerate((plain, spread)):
            g = torch.Generator().manual_seed(40 + i)
            for p in m.net.parameters():
                p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * 0.3)
    pa, pb = save(plain, "plain.safetensors"), save(spread, "spread.safetensors")
    script = load_script("refine_ensemble")
    with pytest.raises(ValueError, match="configuration differs"):
        script.ensemble([pa, pb], "small")
    for order in ([pa, pb], [pb, pa]):  # the head without spread first or second
        tensors, meta = script.ensemble(order, "small", widen=True)
        cfg = json.loads(meta["model_config"])
        assert cfg["spread"] is True and cfg["heads"] == 2
        _assert_ensemble_is_the_mean(tensors, meta, (plain, spread), tmp_path / "ens.safetensors", seed=13)


def test_sample_halves_split_every_per_sample_tensor_and_nothing_else() -> None:
    """Catches halves that overlap or drop samples (even and odd must partition them), a per-pixel
    tensor sliced as if it had samples, and a split of a one-sample batch (no second opinion)."""
    from mcdenoise.models.refine import sample_halves

    rad = torch.arange(5.0).view(1, 5, 1, 1, 1).expand(1, 5, 3, 2, 2)
    batch = {"radiance": rad, "scene_features": torch.ones(1, 4)}
    a, b = sample_halves(batch)
    assert a["radiance"][0, :, 0, 0, 0].tolist() == [0, 2, 4] and b["radiance"][0, :, 0, 0, 0].tolist() == [1, 3]
    assert a["scene_features"] is batch["scene_features"]
    assert sample_halves({"radiance": rad[:, :1]}) is None


def test_spread_features_read_zero_where_the_halves_agree_and_ignore_exposure() -> None:
    """Catches a spread that is not a ratio (it would change with the exposure, which the head's
    other features do not) and one that is not 0 where the base gives the same output from either
    half (a noise-free region)."""
    from mcdenoise.models.refine import N_SPREAD, spread_features

    g = torch.Generator().manual_seed(3)
    lum = torch.rand(1, 1, 9, 9, generator=g, dtype=torch.float64) + 0.1
    a = lum * (1 + 0.2 * torch.rand(lum.shape, generator=g, dtype=torch.float64))
    f = spread_features(lum, a, lum)
    assert f.shape == (1, N_SPREAD, 9, 9) and bool((f > 0).any())
    assert spread_features(lum, a, a).abs().max() < 1e-100  # the 5x5 root's floor, sqrt(tiny)
    # Only the floor EPS (1e-3) is not scaled: against luminances >= 0.1 it moves a ratio by at most 1%.
    torch.testing.assert_close(spread_features(lum * 1e6, a * 1e6, lum * 1e6), f, rtol=2e-2, atol=0)


def test_spread_stage_starts_as_the_base_and_its_head_learns() -> None:
    """Catches the two spread features fed to a head sized without them (a shape error), a spread
    stage that does not start as its base, and a head cut off from the loss. A base that reads pixels
    is refused: it has no samples to halve."""
    model = _model(spread=True).eval()
    batch = synthetic_batch(model, spp=4, height=24, width=20, generator=torch.Generator().manual_seed(6))
    with torch.no_grad():
        out, base = model(batch), model.base(batch)
    assert ((out - base).abs().amax() / base.abs().amax()).item() < 0.02
    model.train()
    model(batch).square().mean().backward()
    missing = [n for n, p in model.net.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]
    assert not missing, f"head parameters without a gradient: {missing[:3]}"
    with pytest.raises(ValueError, match="per-sample base"):
        _model(base="kpcn:small", spread=True)


def test_spread_features_gradients_stay_finite_where_the_halves_agree() -> None:
    """Catches a square root at 0 in the 5x5 spread (its gradient is infinite): with one sample the
    halves agree everywhere, the gradients went NaN, and the receptive-field probe, which follows
    gradients, measured the stage's reach as 0 pixels."""
    from mcdenoise.models.refine import spread_features

    lum = (torch.rand(1, 1, 7, 7, dtype=torch.float64) + 0.1).requires_grad_(True)
    half = lum * 1.0
    spread_features(lum, half, half).sum().backward()
    assert torch.isfinite(lum.grad).all()
