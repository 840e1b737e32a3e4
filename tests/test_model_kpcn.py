"""KPCN / DPCN / single-branch: the paper's preprocessing (Sec. 4.3, 5.1), Eq. 4, sizes (Sec. 5.2)."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from mcdenoise.models.kpcn import FEATURES_PER_BRANCH, KPCN
from mcdenoise.models.registry import build_model, synthetic_batch

EPS = 0.00316
LUM = torch.tensor([0.2126, 0.7152, 0.0722]).view(1, 3, 1, 1)


def _identity_kernel(model: KPCN) -> None:
    """Make every branch output a kernel with (numerically) all weight on its centre."""
    k = model.config.kernel_size
    for br in model.branches.values():
        last = br.net[-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.zero_()
            last.bias[(k * k) // 2] = 60.0


def test_features_follow_paper_preprocessing() -> None:
    model = build_model("kpcn", "small")
    b = synthetic_batch(model, batch=2, height=9, width=11)
    f = model.features(b)
    assert set(f) == {"diffuse", "specular"}
    d, s = f["diffuse"], f["specular"]
    assert d.shape == s.shape == (2, FEATURES_PER_BRANCH, 9, 11)
    irr = b["diffuse"] / (b["albedo_diffuse"] + EPS)
    torch.testing.assert_close(d[:, :3], irr)
    torch.testing.assert_close(s[:, :3], torch.log1p(b["specular"]))
    # Gradients of the colour: forward differences, 0 in the last column/row.
    torch.testing.assert_close(d[:, 3:6, :, :-1], irr[..., 1:] - irr[..., :-1])
    assert (d[:, 3:6, :, -1] == 0).all()
    torch.testing.assert_close(d[:, 6:9, :-1], irr[..., 1:, :] - irr[..., :-1, :])
    # Channel order:
    # [color(3), gx(3), gy(3), n_gx(3), n_gy(3), a_gx(3), a_gy(3), d_gx(1), d_gy(1), var(1), fvar(3)]
    # Depth is log(1 + depth / depth_scale), depth_scale = 1 by default.
    dfeat = torch.log1p(b["depth_diffuse"])
    torch.testing.assert_close(d[:, 21:22, :, :-1], dfeat[..., 1:] - dfeat[..., :-1])
    torch.testing.assert_close(d[:, 22:23, :-1], dfeat[..., 1:, :] - dfeat[..., :-1, :])
    # Eq. 5: relative variance for diffuse, 1/(1+x)^2 for log specular, reduced by luminance.
    dvar = (b["diffuse_variance"] / (b["albedo_diffuse"] + EPS) ** 2 * LUM).sum(1, keepdim=True)
    svar = (b["specular_variance"] / (1 + b["specular"]) ** 2 * LUM).sum(1, keepdim=True)
    torch.testing.assert_close(d[:, 23:24], dvar)
    torch.testing.assert_close(s[:, 23:24], svar)
    torch.testing.assert_close(d[:, 26:27], b["depth_diffuse_variance"] / (1 + b["depth_diffuse"]) ** 2)
    # Feature channels are shared by both branches.
    torch.testing.assert_close(d[:, 9:23], s[:, 9:23])
    torch.testing.assert_close(d[:, 24:], s[:, 24:])


@pytest.mark.parametrize("name", ["kpcn", "dpcn", "kpcn_single"])
def test_features_are_those_of_the_first_diffuse_hit(name: str) -> None:
    """Issue 8 item 5: the paper saves albedo, normal and depth at the first diffuse intersection
    (glass and mirrors show what lies behind them); the first-hit buffers must not be read."""
    model = build_model(name, "small")
    req = set(model.required_channels())
    assert {"albedo_diffuse", "normal_diffuse", "depth_diffuse", "depth_diffuse_variance"} <= req
    assert not req & {"albedo", "normal", "depth", "albedo_variance"}
    # The first-hit form stays available for data without the *_diffuse buffers.
    first = KPCN(replace(model.config, feature_hit="first"))
    assert {"albedo", "normal", "depth"} <= set(first.required_channels())
    b = synthetic_batch(model, height=6, width=7)
    renamed = {k.replace("_diffuse", "") if k.split("_")[0] in ("albedo", "normal", "depth") else k: v
               for k, v in b.items()}
    first.load_state_dict(model.state_dict())
    with torch.no_grad():
        torch.testing.assert_close(first(renamed), model(b))
    with pytest.raises(ValueError, match="feature_hit"):
        KPCN(replace(model.config, feature_hit="second"))


@pytest.mark.parametrize("name", ["kpcn", "kpcn_single"])
def test_crop_features_equal_the_crop_of_the_image_features(name: str) -> None:
    """Issue 8 item 6: depth scaled by each input's maximum made tiles of one image see different
    depth scales (a seam source once we tile). Features of a crop must equal the crop of the
    whole image's features (but the last row/column, whose gradients lose their neighbour)."""
    model = build_model(name, "small")
    b = synthetic_batch(model, batch=2, height=20, width=24)
    b["depth_diffuse"][..., 15:, :] += 50.0  # the far part lies outside the crop
    ys, xs = slice(3, 14), slice(5, 17)
    crop = {k: v[..., ys, xs] for k, v in b.items()}
    whole = model.features(b)
    part = model.features(crop)
    for k in whole:
        torch.testing.assert_close(part[k][..., :-1, :-1], whole[k][..., ys, xs][..., :-1, :-1], rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("name", ["kpcn", "kpcn_single"])
def test_centre_kernel_reproduces_input_through_eq4(name: str) -> None:
    """All kernel weight on the centre: Eq. 4 must undo the preprocessing exactly."""
    model = build_model(name, "small").eval()
    _identity_kernel(model)
    b = synthetic_batch(model, batch=2, height=12, width=13)
    with torch.no_grad():
        out = model(b)
    want = b["diffuse"] + b["specular"] if name == "kpcn" else b["radiance"]
    assert ((out - want).abs() / want.abs().clamp_min(1e-3)).max() < 1e-4


def test_branch_targets_match_branch_outputs_for_identity_kernel() -> None:
    model = build_model("kpcn", "small").eval()
    _identity_kernel(model)
    b = synthetic_batch(model, height=8, width=8)
    with torch.no_grad():
        br = model.forward_branches(b)
    tg = model.branch_targets({"diffuse": b["diffuse"], "specular": b["specular"]}, b)
    for k in ("diffuse", "specular"):
        torch.testing.assert_close(br[k], tg[k], rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(model.recombine(br, b), model(b))


def test_kernel_output_is_convex_combination_even_at_borders() -> None:
    """Softmax kernels renormalised over the image: a constant irradiance stays constant everywhere."""
    torch.manual_seed(0)
    model = build_model("kpcn", "small").eval()
    b = synthetic_batch(model, height=10, width=10)
    b["diffuse"] = 0.7 * (b["albedo_diffuse"] + EPS)
    b["specular"] = torch.full_like(b["specular"], 2.0)
    with torch.no_grad():
        br = model.forward_branches(b)
    torch.testing.assert_close(br["diffuse"], torch.full_like(br["diffuse"], 0.7))
    torch.testing.assert_close(br["specular"], torch.full_like(br["specular"], torch.log1p(torch.tensor(2.0)).item()))


def _expected_params(cin: int, ch: int, k: int, layers: int, out: int) -> int:
    n = cin * ch * k * k + ch
    n += (layers - 2) * (ch * ch * k * k + ch)
    return n + ch * out * k * k + out


def test_paper_sizes() -> None:
    """Sec. 5.2: 9 convolutions of 100 5x5 kernels per branch; 21x21 kernels (KPCN) or RGB (DPCN).

    The counts are literals (worked out by hand from the paper's architecture: 27 inputs, 9 layers
    x 100 channels x 5x5, 441 or 3 outputs), so that a change of the code cannot move the
    expectation with it."""
    counts = {name: sum(p.numel() for p in build_model(name, "paper").parameters())
              for name in ("kpcn", "dpcn", "kpcn_single")}
    # One branch: 27*100*25+100 + 7*(100*100*25+100) + 100*441*25+441 = 2,921,241.
    assert counts == {"kpcn": 5_842_482, "dpcn": 3_651_606, "kpcn_single": 2_921_241}
    assert _expected_params(FEATURES_PER_BRANCH, 100, 5, 9, 21 * 21) == 2_921_241
    assert _expected_params(FEATURES_PER_BRANCH, 100, 5, 9, 3) == 3_651_606 // 2
    kpcn = build_model("kpcn", "paper")
    assert FEATURES_PER_BRANCH == 27 and kpcn.config.kernel_size == 21
    assert sum(isinstance(m, torch.nn.Conv2d) for m in kpcn.branches["diffuse"].modules()) == 9
    single = build_model("kpcn_single", "paper")
    assert set(single.required_channels()) >= {"radiance", "radiance_variance", "albedo_diffuse", "normal_diffuse", "depth_diffuse"}
    assert "radiance" not in kpcn.required_channels()


def _uniform_kernel(model: KPCN) -> None:
    """Zero the last layer: every logit 0, so each kernel is uniform over its in-image taps."""
    for br in model.branches.values():
        with torch.no_grad():
            br.net[-1].weight.zero_()
            br.net[-1].bias.zero_()


def _box_mean(x: torch.Tensor, k: int) -> torch.Tensor:
    """Plain reference: mean over the in-image pixels of each KxK window."""
    return torch.nn.functional.avg_pool2d(x, k, stride=1, padding=k // 2, count_include_pad=False)


def test_branches_filter_in_the_transformed_domain() -> None:
    """Mutation "radiance fed without log compression" (issue 8 item 13), applied to features and
    Eq. 4 together so that a centre kernel still reproduces the input: with a uniform kernel the
    output must be the box mean of irradiance times albedo (diffuse) and exp(box mean of
    log(1 + x)) - 1 (specular, single-branch radiance), not the box mean of the radiance."""
    torch.manual_seed(0)
    k = build_model("kpcn", "small").config.kernel_size
    kpcn = build_model("kpcn", "small").eval()
    single = build_model("kpcn_single", "small").eval()
    _uniform_kernel(kpcn)
    _uniform_kernel(single)
    b = synthetic_batch(kpcn, height=12, width=14)
    bs = synthetic_batch(single, height=12, width=14)
    a = b["albedo_diffuse"] + EPS
    want = a * _box_mean(b["diffuse"] / a, k) + torch.expm1(_box_mean(torch.log1p(b["specular"]), k))
    want_single = torch.expm1(_box_mean(torch.log1p(bs["radiance"]), k))
    with torch.no_grad():
        torch.testing.assert_close(kpcn(b), want, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(single(bs), want_single, rtol=1e-5, atol=1e-6)
    # The transforms matter on this data (else the test could not tell them apart).
    assert (want_single - _box_mean(bs["radiance"], k)).abs().max() > 0.1
    assert (a * _box_mean(b["diffuse"] / a, k) - _box_mean(b["diffuse"], k)).abs().max() > 0.1


@pytest.mark.parametrize("name", ["kpcn", "kpcn_single"])
def test_kernel_is_the_softmax_of_the_raw_head_output(name: str) -> None:
    """Mutation "ReLU on KPCN's kernel logits" (issue 8 item 13): the kernel must be the softmax
    (over in-image taps) of the last layer's raw, signed output, checked against a plain unfold."""
    torch.manual_seed(1)
    model = build_model(name, "small").eval()
    k = model.config.kernel_size
    b = synthetic_batch(model, batch=2, height=10, width=11)
    with torch.no_grad():
        feats = model.features(b)
        out = model.forward_branches(b)
        for br, x in feats.items():
            z = model.branches[br](x)  # (B, K*K, H, W)
            assert (z < 0).float().mean() > 0.2  # signed logits: a ReLU would change them
            inside = torch.nn.functional.unfold(torch.ones_like(x[:, :1]), k, padding=k // 2) > 0  # (B, K*K, H*W)
            zz = z.flatten(2).masked_fill(~inside, float("-inf"))
            w = torch.softmax(zz, dim=1)  # (B, K*K, H*W)
            cols = torch.nn.functional.unfold(x[:, :3], k, padding=k // 2).view(x.shape[0], 3, k * k, -1)
            want = (cols * w[:, None]).sum(2).view_as(x[:, :3])
            torch.testing.assert_close(out[br], want, rtol=1e-5, atol=1e-6)


def test_sharply_peaked_kernel_is_reachable_through_negative_logits() -> None:
    """Mutation "ReLU on KPCN's kernel logits": a kernel whose off-centre logits are very negative
    must reproduce its centre pixel (a ReLU clips them to 0 and the kernel becomes a box blur)."""
    model = build_model("kpcn", "small").eval()
    k = model.config.kernel_size
    for br in model.branches.values():
        with torch.no_grad():
            br.net[-1].weight.zero_()
            br.net[-1].bias.fill_(-40.0)
            br.net[-1].bias[(k * k) // 2] = 0.0
    b = synthetic_batch(model, height=12, width=12)
    with torch.no_grad():
        out = model(b)
    want = b["diffuse"] + b["specular"]
    assert ((out - want).abs() / want.abs().clamp_min(1e-3)).max() < 1e-4


@pytest.mark.parametrize("name", ["kpcn", "dpcn", "kpcn_single"])
def test_every_parameter_gets_a_gradient_and_every_input_matters(name: str) -> None:
    """Every parameter tensor receives a non-zero gradient, and changing any one input channel
    (colour, variance, albedo, normal, depth and their variances) changes the output: catches an
    input group dropped from the features, or a layer cut off from the loss."""
    torch.manual_seed(2)
    model = build_model(name, "small")
    b = synthetic_batch(model, height=8, width=8)
    out = model(b)
    (out - 0.5 * b.get("radiance", out.detach())).abs().mean().backward()
    for pname, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, pname
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        # Compared in the branches' own domains, where an input's effect is not dwarfed by
        # exp() of bright specular pixels; an input that no path reaches changes nothing at all.
        base = model.forward_branches(b)
        for ch in model.required_channels():
            changed = dict(b)
            changed[ch] = b[ch] * (1.0 + torch.rand(b[ch].shape, generator=g)) + 0.05
            new = model.forward_branches(changed)
            diff = max((new[k] - base[k]).abs().max().item() for k in base)
            assert diff > 1e-5, ch


def test_dpcn_outputs_transformed_colour_directly() -> None:
    model = build_model("dpcn", "small").eval()
    b = synthetic_batch(model, height=8, width=9)
    with torch.no_grad():
        br = model.forward_branches(b)
        feats = model.features(b)
        z = model.branches["specular"](feats["specular"])
    torch.testing.assert_close(br["specular"], z)
    out = model(b)
    torch.testing.assert_close(out, (b["albedo_diffuse"] + EPS) * br["diffuse"] + torch.expm1(br["specular"]))


def test_per_branch_pretraining_then_finetune_step() -> None:
    """The paper's schedule: L1 per branch in the transformed domain, then L1 on the recombined image."""
    torch.manual_seed(0)
    model = build_model("kpcn", "small")
    b = synthetic_batch(model, height=12, width=12)
    ref = {"diffuse": b["diffuse"] * 0.5, "specular": b["specular"] * 0.5}
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    br = model.forward_branches(b)
    tg = model.branch_targets(ref, b)
    loss = sum((br[k] - tg[k]).abs().mean() for k in br)
    loss.backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())
    opt.step()
    opt.zero_grad()
    out = model(b)
    (out - (ref["diffuse"] + ref["specular"])).abs().mean().backward()
    assert torch.isfinite(out).all()


def test_odd_size_and_dtype_float64() -> None:
    model = build_model("kpcn", "small").double().eval()
    b = synthetic_batch(model, height=7, width=5, dtype=torch.float64)
    with torch.no_grad():
        out = model(b)
    assert out.shape == (1, 3, 7, 5) and out.dtype == torch.float64


def test_missing_channel_named() -> None:
    model = build_model("kpcn", "small")
    b = synthetic_batch(model, height=5, width=5)
    del b["specular_variance"]
    with pytest.raises(ValueError, match="specular_variance"):
        model(b)


@pytest.mark.parametrize("band_bytes", [1, 3000, 1 << 30])
def test_banded_kernel_application_equals_whole_image(band_bytes: int) -> None:
    """Bug caught: the inference-only banded mask/softmax/gather (row offset of the border mask
    wrong, a band's last rows dropped, a band reading the wrong image rows) differing from the
    whole-image training path. Bands of 1 row, a few rows (several bands, the last one short) and
    the whole image; float64 so only the algebra is compared."""
    from mcdenoise.models.kpcn import _apply_kernels_banded, _mask_out_of_image_taps
    from mcdenoise.ops.gather import gather

    g = torch.Generator().manual_seed(3)
    k, h, w = 5, 13, 9
    color = torch.rand((2, 3, h, w), generator=g, dtype=torch.float64)
    logits = torch.randn((2, k * k, h, w), generator=g, dtype=torch.float64) * 3
    want = gather(color, torch.softmax(_mask_out_of_image_taps(logits, k), dim=1))
    got = _apply_kernels_banded(color, logits, k, band_bytes=band_bytes)
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    # A channels_last logit tensor (what a bfloat16 trunk hands over) gives the same result.
    got_cl = _apply_kernels_banded(color, logits.contiguous(memory_format=torch.channels_last), k, band_bytes=3000)
    torch.testing.assert_close(got_cl, want, rtol=1e-12, atol=1e-12)


def test_model_forward_no_grad_equals_grad_path() -> None:
    """Bug caught: the model taking the banded path under no_grad with other kernels than the
    training path would (e.g. a branch's logits not masked): both forwards must agree."""
    torch.manual_seed(0)
    m = build_model("kpcn", "small").double().eval()
    batch = synthetic_batch(m, height=11, width=14, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        a = m(batch)
    b = m(batch).detach()
    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("h,w,k", [(2, 3, 9), (1, 1, 3), (7, 4, 5), (9, 11, 3)])
def test_border_mask_equals_broadcast_mask_on_every_band(h: int, w: int, k: int) -> None:
    """Bug caught: the in-place border mask missing a ring (off-by-one in d), masking interior
    pixels, or mis-placing the top/bottom rows of a band that starts inside the image; images
    smaller than the kernel included."""
    from mcdenoise.models.kpcn import _mask_border_taps_, _mask_out_of_image_taps

    z = torch.randn(2, k * k, h, w, dtype=torch.float64)
    want = _mask_out_of_image_taps(z, k)
    for rows in range(1, h + 1):
        for r0 in range(0, h, rows):
            band = z[:, :, r0 : r0 + rows].clone()
            got = _mask_border_taps_(band, k, r0, h)
            assert torch.equal(got, want[:, :, r0 : r0 + rows]), (rows, r0)


def test_window_variance_equals_a_loop_over_in_image_windows() -> None:
    """Float64 against a per-pixel loop: catches padding counted as pixels at the borders (the
    border variance would mix in zeros), a biased divisor, or an off-centre window."""
    from mcdenoise.models.kpcn import window_variance

    g = torch.Generator().manual_seed(0)
    x = torch.rand(2, 3, 7, 9, generator=g, dtype=torch.float64) * 4
    k, r = 5, 2
    got = window_variance(x, k)
    want = torch.empty_like(x)
    for i in range(7):
        for j in range(9):
            win = x[..., max(0, i - r) : i + r + 1, max(0, j - r) : j + r + 1].flatten(-2)
            want[..., i, j] = win.var(dim=-1, unbiased=False)
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    assert (window_variance(torch.full((1, 1, 6, 6), 3.0, dtype=torch.float64), k) == 0).all()


@pytest.mark.parametrize("name", ["kpcn", "kpcn_single"])
def test_pixel_preset_reads_no_variance_and_every_input_matters(name: str) -> None:
    """The ``pixel`` preset runs on inputs without samples: catches a variance channel still
    required (Blender and pbrt files would be refused), a first-hit feature not read, a window
    variance that leaves the crop equal to the crop of the whole image only in the interior too
    narrowly (a seam source), and a constant image that does not stay constant."""
    model = build_model(name, "pixel")
    req = model.required_channels()
    assert not [c for c in req if c.endswith("_variance")]
    assert {"albedo", "normal", "depth"} <= set(req)
    torch.manual_seed(1)
    b = synthetic_batch(model, batch=1, height=20, width=24)
    out = model(b)
    (out - 0.5).abs().mean().backward()
    for pname, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, pname
    with torch.no_grad():
        base = model.forward_branches(b)
        for ch in req:
            changed = dict(b)
            changed[ch] = b[ch] * 1.5 + 0.05
            new = model.forward_branches(changed)
            assert max((new[k] - base[k]).abs().max().item() for k in base) > 1e-5, ch
        ys, xs = slice(3, 16), slice(5, 19)
        part = model.features({k: v[..., ys, xs] for k, v in b.items()})
        whole = model.features(b)
        r = model.config.variance_window // 2
        for k in whole:  # away from the crop's edge by the window radius (and the gradient's pixel)
            torch.testing.assert_close(part[k][..., r:-r - 1, r:-r - 1], whole[k][..., ys, xs][..., r:-r - 1, r:-r - 1],
                                       rtol=1e-5, atol=1e-6)
        flat = {k: torch.full_like(v, 0.7) for k, v in b.items()}
        torch.testing.assert_close(model.eval()(flat), torch.full_like(out, 1.4 if "specular" in b else 0.7),
                                   rtol=1e-4, atol=1e-5)
