"""The sample-consistency clamp (mcdenoise/models/consistency.py) and the models that apply it.

Each test names the bug it catches."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mcdenoise.infer.sources import from_arrays
from mcdenoise.models import build_model, synthetic_batch
from mcdenoise.models.consistency import PRIOR, WINDOW, consistency_clamp, sample_bounds
from test_model_exposure import assert_sample_tiles_match_whole

SAMPLE_MODELS = ["sbmc", "layer"]


def _samples(s: int = 4, h: int = 9, w: int = 11, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    # Heavy-tailed like Monte Carlo: mostly dim, now and then a bright sample.
    x = torch.rand(1, s, 3, h, w, generator=g, dtype=torch.float64) ** 4 * 5
    return x


@pytest.mark.parametrize("box", ["mean", "median"])
def test_bounds_match_a_plain_loop(box: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches a biased variance (S instead of S - 1), zero padding at the border instead of the
    image's own pixels, or the shrinkage weights swapped; for the median box, bands of rows that
    lose the box's rows above or below at their seams (bands of 4 rows here): the bounds equal a
    per-pixel loop in float64."""
    from mcdenoise.models import consistency

    monkeypatch.setattr(consistency, "MEDIAN_BAND", 4)
    x = _samples()
    k = 2.5
    lo, hi = sample_bounds(x, k, box)
    stat = np.mean if box == "mean" else np.median
    a = x[0].numpy()
    s, c, h, w = a.shape
    var = a.var(axis=0, ddof=1)
    r = WINDOW // 2
    for ch in range(c):
        for y in range(h):
            for xx in range(w):
                box = [var[ch, min(max(y + dy, 0), h - 1), min(max(xx + dx, 0), w - 1)]
                       for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
                shrunk = ((s - 1) * var[ch, y, xx] + PRIOR * stat(box)) / (s - 1 + PRIOR)
                half = k * np.sqrt(shrunk / s)
                m = a[:, ch, y, xx].mean()
                assert lo[0, ch, y, xx].item() == pytest.approx(m - half, rel=1e-12, abs=1e-12)
                assert hi[0, ch, y, xx].item() == pytest.approx(m + half, rel=1e-12, abs=1e-12)


def test_clamp_keeps_what_lies_inside_and_bounds_the_rest() -> None:
    """Catches minimum and maximum swapped (every pixel pinned to a bound) or a clamp that moves
    pixels already inside the interval."""
    x = _samples(seed=1)
    g = torch.Generator().manual_seed(2)
    out = torch.rand(1, 3, 9, 11, generator=g, dtype=torch.float64) * 3
    lo, hi = sample_bounds(x, 2.0)
    got = consistency_clamp(out, x, 2.0)
    assert bool(((got >= lo) & (got <= hi)).all())
    inside = (out >= lo) & (out <= hi)
    assert inside.any() and (~inside).any()
    assert torch.equal(got[inside], out[inside])


def test_samples_that_agree_everywhere_give_their_value() -> None:
    """A constant image stays constant: where every sample of every pixel agrees, the variance is
    0 and any output is brought back to the samples' value (catches an epsilon that lets a
    network's blur through)."""
    value = torch.rand(1, 1, 3, 8, 8, dtype=torch.float64)
    x = value.expand(1, 5, 3, 8, 8).clone()
    out = torch.rand(1, 3, 8, 8, dtype=torch.float64)
    # The mean of five equal numbers may round by an ulp, and so may their spread around it: a few
    # ulps of float64, where a clamp that let the output through would be off by O(1).
    torch.testing.assert_close(consistency_clamp(out, x, 3.0), value[:, 0], rtol=1e-13, atol=0)


def test_sample_order_does_not_matter() -> None:
    """Shuffled samples give the same output (catches a bound built from the first samples only)."""
    x = _samples(s=6, seed=3)
    out = torch.rand(1, 3, 9, 11, dtype=torch.float64) * 2
    perm = torch.randperm(6, generator=torch.Generator().manual_seed(4))
    torch.testing.assert_close(consistency_clamp(out, x[:, perm], 2.0), consistency_clamp(out, x, 2.0),
                               rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("scale", [1e-3, 7.0, 1e4])
def test_follows_exposure(scale: float) -> None:
    """The same picture brighter gives the same picture brighter (catches an absolute epsilon in
    the variance, which would clamp dim images harder than bright ones)."""
    x = _samples(seed=5)
    out = torch.rand(1, 3, 9, 11, dtype=torch.float64) * 2
    torch.testing.assert_close(consistency_clamp(out * scale, x * scale, 2.0), consistency_clamp(out, x, 2.0) * scale,
                               rtol=1e-10, atol=0)


def test_none_and_one_sample_pass_through() -> None:
    """Catches a clamp applied without a variance estimate (one sample pins the output to it)."""
    out = torch.rand(1, 3, 5, 5)
    assert consistency_clamp(out, torch.rand(1, 1, 3, 5, 5), 2.0) is out
    assert consistency_clamp(out, torch.rand(1, 4, 3, 5, 5), None) is out


def test_gradients_reach_the_output_and_the_samples() -> None:
    """gradcheck in float64 (a clamp's kinks have measure zero on random inputs)."""
    x = _samples(s=3, h=6, w=6, seed=6).requires_grad_()
    out = (torch.rand(1, 3, 6, 6, dtype=torch.float64) * 2).requires_grad_()
    assert torch.autograd.gradcheck(lambda o, s: consistency_clamp(o, s, 1.5), (out, x))


@pytest.mark.parametrize("name", SAMPLE_MODELS)
def test_models_apply_it_to_their_own_output(name: str) -> None:
    """Catches a model that ignores its ``consistency`` or clamps before the emitter pass-through
    and the exposure's way back (bounds at the wrong brightness)."""
    torch.manual_seed(0)
    model = build_model(name, "small", autoexposure=0.18).eval()
    batch = synthetic_batch(model, spp=4, height=24, width=24)
    with torch.no_grad():
        raw = model(batch)
        model.config.consistency = 1.0
        clamped = model(batch)
    torch.testing.assert_close(clamped, consistency_clamp(raw, batch["radiance"], 1.0), rtol=0, atol=0)
    assert not torch.equal(clamped, raw)  # k = 1 binds somewhere on random inputs


@pytest.mark.parametrize("name", SAMPLE_MODELS)
def test_min_spp_gates_the_clamp_by_the_sample_count(name: str) -> None:
    """``consistency_min_spp`` 8: catches a gate that compares with the wrong count (the stored
    spp, a tile's, an off-by-one at exactly 8), or one that leaks into the default: below 8 samples
    the output is the unclamped one, from 8 it is today's clamp, and the default (2) clamps at 4."""
    torch.manual_seed(0)
    model = build_model(name, "small", autoexposure=0.18).eval()
    for spp, clamps in ((4, False), (7, False), (8, True)):
        batch = synthetic_batch(model, spp=spp, height=24, width=24)
        with torch.no_grad():
            model.config.consistency, model.config.consistency_min_spp = None, 2
            raw = model(batch)
            model.config.consistency = 1.0
            default = model(batch)
            model.config.consistency_min_spp = 8
            gated = model(batch)
        assert not torch.equal(default, raw)  # k = 1 binds somewhere on random inputs
        torch.testing.assert_close(gated, default if clamps else raw, rtol=0, atol=0)


def test_pixel_clamp_min_spp_matches_the_sample_clamp() -> None:
    """The pixel form obeys the same gate: catches ``denoise`` and ``eval`` clamping a pixel model
    below its ``consistency_min_spp`` while a sample model would not."""
    from mcdenoise.data.stats import pixel_stats
    from mcdenoise.models.consistency import pixel_consistency_clamp

    out = torch.rand(1, 3, 9, 11) * 3
    for s in (4, 8):
        x = _samples(s=s, seed=8).float()
        mean, var_mean = pixel_stats(x[0].numpy())
        got = pixel_consistency_clamp(out[0].numpy(), mean, var_mean, s, 2.0, 8)
        np.testing.assert_allclose(got, consistency_clamp(out, x, 2.0, 8)[0].numpy(), rtol=1e-5, atol=1e-6)
        assert np.array_equal(got, out[0].numpy()) == (s < 8)


def test_median_box_keeps_a_light_from_loosening_the_dark_pixels_beside_it() -> None:
    """The reason for the median box: a dark pixel whose samples all agree beside a bright, noisy
    column gets a bound from its dark neighbours, not from the column. Catches a median taken over
    the wrong axis (samples or channels) or a box that still averages: with the mean box the
    bound is loose, with the median box it is the dark side's."""
    g = torch.Generator().manual_seed(3)
    x = torch.zeros(1, 4, 3, 9, 9, dtype=torch.float64)
    x[..., 4:] = 0.1 * torch.rand(1, 4, 3, 9, 5, generator=g, dtype=torch.float64)  # dim, slightly noisy
    x[..., 0] = 1000 * torch.rand(1, 4, 3, 9, generator=g, dtype=torch.float64)  # a bright, noisy column
    lo_mean, hi_mean = sample_bounds(x, 3.0, "mean")
    lo_med, hi_med = sample_bounds(x, 3.0, "median")
    # Pixel (4, 2): its four samples are all 0; the column is two pixels away, inside its box.
    assert hi_mean[0, :, 4, 2].min().item() > 100
    assert hi_med[0, :, 4, 2].max().item() < 1e-9  # most of its box is exactly dark: a median of 0
    assert torch.all(hi_med[0, :, :, 0] > 100)  # the column keeps the loose bound of its own variance


def test_median_box_gradients() -> None:
    """gradcheck in float64 through the median box (the selected element carries the gradient)."""
    x = _samples(s=3, h=6, w=6, seed=9).requires_grad_()
    out = (torch.rand(1, 3, 6, 6, dtype=torch.float64) * 2).requires_grad_()
    assert torch.autograd.gradcheck(lambda o, s: consistency_clamp(o, s, 1.5, 2, "median"), (out, x))


def test_median_box_tiles_match_the_whole_image() -> None:
    """Catches a median box that reads past the tile overlap (its reach is the mean box's, 2 px)."""
    torch.manual_seed(0)
    model = build_model("layer", "small", autoexposure=0.18, consistency=1.5, consistency_box="median").eval()
    assert_sample_tiles_match_whole(model, spp=3)


def test_refuses_an_unknown_box() -> None:
    with pytest.raises(ValueError, match="consistency_box"):
        build_model("sbmc", "small", consistency=2.0, consistency_box="max")


@pytest.mark.parametrize("bad", [0, -2, 2.5, True])
def test_refuses_a_min_spp_that_is_not_a_count(bad) -> None:
    with pytest.raises(ValueError, match="consistency_min_spp"):
        build_model("layer", "small", consistency=4.0, consistency_min_spp=bad)


@pytest.mark.parametrize("k", [0.0, -1.0])
def test_refuses_a_non_positive_k(k: float) -> None:
    with pytest.raises(ValueError, match="consistency"):
        build_model("sbmc", "small", consistency=k)


def test_tiles_match_the_whole_image() -> None:
    """Catches a tile overlap that misses the clamp's neighbourhood (seams where the box of a
    border pixel reads the tile's edge instead of the image)."""
    torch.manual_seed(0)
    model = build_model("layer", "small", autoexposure=0.18, consistency=1.5).eval()
    assert_sample_tiles_match_whole(model, spp=3)


@pytest.mark.parametrize("box", ["mean", "median"])
def test_pixel_form_equals_the_sample_form(box: str) -> None:
    """A pixel model's clamp (from the input's per-pixel mean and variance of the mean) and a sample
    model's (from the samples) are one rule: catches the two paths drifting apart (a variance of
    the samples where the variance of the mean is meant, other shrinkage weights)."""
    from mcdenoise.data.stats import pixel_stats
    from mcdenoise.models.consistency import pixel_consistency_clamp

    x = _samples(s=6, seed=7).float()
    out = torch.rand(1, 3, 9, 11) * 3
    mean, var_mean = pixel_stats(x[0].numpy())
    got = pixel_consistency_clamp(out[0].numpy(), mean, var_mean, 6, 2.0, 2, box)
    np.testing.assert_allclose(got, consistency_clamp(out, x, 2.0, 2, box)[0].numpy(), rtol=1e-5, atol=1e-6)


def _wskp_inputs(with_variance: bool):
    from mcdenoise.data.stats import pixel_stats

    g = np.random.default_rng(0)
    s, h, w = 4, 24, 24
    samples = (g.random((s, 3, h, w), dtype=np.float32) ** 4) * 3
    mean, var_mean = pixel_stats(samples)
    albedo = np.full((3, h, w), 0.5, np.float32)
    normal = np.zeros((3, h, w), np.float32)
    normal[2] = 1
    depth = np.ones((1, h, w), np.float32)
    feats = {"radiance_variance": var_mean} if with_variance else None
    return from_arrays(mean, albedo=albedo, normal=normal, depth=depth, features=feats,
                       samples={"radiance": samples} if with_variance else None), mean, var_mean


def test_denoise_clamps_a_pixel_model_where_the_input_has_variances() -> None:
    """Catches a pixel model's ``consistency`` ignored by ``denoise``, or applied without the
    input's variance (a Blender file has none: there it must pass unchanged)."""
    from mcdenoise.infer.run import denoise_inputs
    from mcdenoise.models.consistency import pixel_consistency_clamp

    torch.manual_seed(0)
    model = build_model("wskp", "small", autoexposure=0.18).eval()
    inp, mean, var_mean = _wskp_inputs(True)
    raw, info = denoise_inputs(inp, model, device="cpu", tile=None, progress=False)
    assert info.consistency == ""
    model.config.consistency = 1.0
    inp, _, _ = _wskp_inputs(True)
    clamped, info = denoise_inputs(inp, model, device="cpu", tile=None, progress=False)
    np.testing.assert_array_equal(clamped, pixel_consistency_clamp(raw, mean, var_mean, 4, 1.0))
    assert not np.array_equal(clamped, raw)
    assert info.consistency.startswith("each pixel within 1 standard errors")
    inp, _, _ = _wskp_inputs(False)
    alone, info = denoise_inputs(inp, model, device="cpu", tile=None, progress=False)
    np.testing.assert_array_equal(alone, raw)
    assert info.consistency.startswith("not applied")  # the user is told, not left to guess


def test_denoise_says_when_the_gate_leaves_the_output_unclamped() -> None:
    """Catches ``denoise`` reporting a clamp that the sample count switched off (the user would
    believe each pixel is bounded by its samples when it is not), for a pixel and a sample model."""
    from mcdenoise.infer.run import denoise_inputs

    torch.manual_seed(0)
    model = build_model("wskp", "small", autoexposure=0.18).eval()
    raw, _ = denoise_inputs(_wskp_inputs(True)[0], model, device="cpu", tile=None, progress=False)
    model.config.consistency, model.config.consistency_min_spp = 1.0, 8
    gated, info = denoise_inputs(_wskp_inputs(True)[0], model, device="cpu", tile=None, progress=False)
    np.testing.assert_array_equal(gated, raw)
    assert info.consistency == "not applied (consistency 1 acts from 8 spp): the input has 4"
    layer = build_model("layer", "small", autoexposure=0.18, consistency=1.0, consistency_min_spp=8).eval()
    for spp, note in ((4, "not applied (consistency 1 acts from 8 spp): the input has 4"),
                      (8, "each pixel within 1 standard errors of its own samples' mean")):
        b = synthetic_batch(layer, batch=1, spp=spp, height=16, width=16)
        samples = {k: v[0].numpy() for k, v in b.items() if k != "scene_features"}
        inp = from_arrays(samples["radiance"].mean(axis=0), samples=samples, scene_features=b["scene_features"][0].numpy())
        assert denoise_inputs(inp, layer, device="cpu", tile=None, progress=False)[1].consistency == note


def test_eval_clamps_a_pixel_model_with_the_k_samples_statistics(tmp_path) -> None:
    """Catches ``eval`` scoring a pixel model without its ``consistency`` (or with the statistics
    of every stored sample instead of the k it evaluates): the table would not be what ``denoise``
    gives on the same k samples."""
    from mcdenoise.data.format import ImageFolder, ImageMeta
    from mcdenoise.data.stats import pixel_stats
    from mcdenoise.data.writer import write_image
    from mcdenoise.eval.methods import Inputs, ModelMethod
    from mcdenoise.models.consistency import pixel_consistency_clamp

    g = np.random.default_rng(1)
    s, h, w = 8, 16, 16
    chans = ["radiance", "albedo", "normal", "depth"]
    normal = np.zeros((s, 3, h, w), np.float32)
    normal[:, 2] = 1
    samples = {"radiance": (g.random((s, 3, h, w), dtype=np.float32) ** 4) * 3,
               "albedo": np.full((s, 3, h, w), 0.5, np.float32), "normal": normal,
               "depth": np.ones((s, 1, h, w), np.float32)}
    write_image(tmp_path / "im", meta=ImageMeta(width=w, height=h, spp=s, channels=chans), samples=samples)
    torch.manual_seed(0)
    model = build_model("wskp", "small", autoexposure=0.18, consistency=1.0).eval()
    method = ModelMethod("wskp", model, {"name": "wskp"}, "cpu")
    x = Inputs(ImageFolder(tmp_path / "im"), 4)
    got = method.run(method.prepare(x))
    model.config.consistency = None
    raw = method.run(method.prepare(x))
    mean, var_mean = pixel_stats(samples["radiance"][:4])
    np.testing.assert_allclose(got, pixel_consistency_clamp(raw, mean, var_mean, 4, 1.0), rtol=1e-6, atol=1e-7)
    assert not np.allclose(got, raw)


def test_probe_rule_picks_the_lowest_sum_among_settings_nowhere_below_the_unclamped_psnr() -> None:
    """scripts/consistency_probe.py's rule: catches a setting admitted though its PSNR is below the
    unclamped at one spp, a choice by the wrong spp's figure instead of the sum, or a choice made
    when nothing is eligible."""
    from repo_scripts import load_script

    probe = load_script("consistency_probe")
    figures = {"none": {4: (0.10, 26.0), 8: (0.08, 27.0)},
               "k 3": {4: (0.05, 25.9), 8: (0.05, 27.1)},  # lowest sum, but below at 4 spp
               "k 4": {4: (0.10, 26.0), 8: (0.07, 27.1)},
               "k 3@8": {4: (0.10, 26.0), 8: (0.06, 27.0)}}
    assert probe.rule_choice(figures) == (["k 3@8", "k 4"], "k 3@8")
    assert probe.rule_choice({"none": figures["none"], "k 3": figures["k 3"]}) == ([], "none")
    assert probe.parse_k("4m@8") == (4.0, 8, "median") and probe.parse_k("2.5") == (2.5, 2, "mean")


def test_probe_paired_lines_give_the_candidate_minus_the_first_model_to_five_decimals() -> None:
    """scripts/consistency_probe.py's paired figures: catches the difference taken the wrong way round
    (shipped minus candidate), a PSNR difference rounded to the 4 decimals at which two models tie,
    a ratio of arithmetic instead of geometric means, and the first model paired with itself."""
    from repo_scripts import load_script

    probe = load_script("consistency_probe")
    ship = np.array([[0.10, 26.00000], [0.40, 27.00000]])
    cand = np.array([[0.05, 26.00004], [0.40, 27.00002]])  # PSNR +0.00003 dB: a tie at 4 decimals
    lines = probe.paired_lines({("ship", "k 4", 4): ship, ("cand", "k 4", 4): cand,
                                ("cand", "none", 4): cand}, "ship")
    assert lines == [f"paired spp  4 cand k 4 vs ship k 4: relMSE geo ratio {np.sqrt(0.5):.5f}, "
                     "PSNR +0.00003 dB, higher on 2 of 2"]
