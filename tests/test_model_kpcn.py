"""KPCN / DPCN / single-branch: the paper's preprocessing (Sec. 4.3, 5.1), Eq. 4, sizes (Sec. 5.2)."""

from __future__ import annotations

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
    irr = b["diffuse"] / (b["albedo"] + EPS)
    torch.testing.assert_close(d[:, :3], irr)
    torch.testing.assert_close(s[:, :3], torch.log1p(b["specular"]))
    # Gradients of the colour: forward differences, 0 in the last column/row.
    torch.testing.assert_close(d[:, 3:6, :, :-1], irr[..., 1:] - irr[..., :-1])
    assert (d[:, 3:6, :, -1] == 0).all()
    torch.testing.assert_close(d[:, 6:9, :-1], irr[..., 1:, :] - irr[..., :-1, :])
    # Depth gradient uses depth scaled to [0, 1] per image: x-gradient channel is 9 + 2*3 + 3 + ... order:
    # [color(3), gx(3), gy(3), n_gx(3), n_gy(3), a_gx(3), a_gy(3), d_gx(1), d_gy(1), var(1), fvar(3)]
    dmax = b["depth"].amax(dim=(1, 2, 3), keepdim=True)
    dscaled = b["depth"] / dmax
    torch.testing.assert_close(d[:, 21:22, :, :-1], dscaled[..., 1:] - dscaled[..., :-1])
    # Eq. 5: relative variance for diffuse, 1/(1+x)^2 for log specular, reduced by luminance.
    dvar = (b["diffuse_variance"] / (b["albedo"] + EPS) ** 2 * LUM).sum(1, keepdim=True)
    svar = (b["specular_variance"] / (1 + b["specular"]) ** 2 * LUM).sum(1, keepdim=True)
    torch.testing.assert_close(d[:, 23:24], dvar)
    torch.testing.assert_close(s[:, 23:24], svar)
    torch.testing.assert_close(d[:, 26:27], b["depth_variance"] / dmax**2)
    # Feature channels are shared by both branches.
    torch.testing.assert_close(d[:, 9:23], s[:, 9:23])
    torch.testing.assert_close(d[:, 24:], s[:, 24:])


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
    b["diffuse"] = 0.7 * (b["albedo"] + EPS)
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
    """Sec. 5.2: 9 convolutions of 100 5x5 kernels per branch; 21x21 kernels (KPCN) or RGB (DPCN)."""
    kpcn = build_model("kpcn", "paper")
    dpcn = build_model("dpcn", "paper")
    single = build_model("kpcn_single", "paper")
    per_branch = _expected_params(FEATURES_PER_BRANCH, 100, 5, 9, 21 * 21)
    assert sum(p.numel() for p in kpcn.parameters()) == 2 * per_branch
    assert sum(p.numel() for p in single.parameters()) == per_branch
    assert sum(p.numel() for p in dpcn.parameters()) == 2 * _expected_params(FEATURES_PER_BRANCH, 100, 5, 9, 3)
    assert sum(isinstance(m, torch.nn.Conv2d) for m in kpcn.branches["diffuse"].modules()) == 9
    assert set(single.required_channels()) >= {"radiance", "radiance_variance", "albedo", "normal", "depth"}
    assert "radiance" not in kpcn.required_channels()


def test_dpcn_outputs_transformed_colour_directly() -> None:
    model = build_model("dpcn", "small").eval()
    b = synthetic_batch(model, height=8, width=9)
    with torch.no_grad():
        br = model.forward_branches(b)
        feats = model.features(b)
        z = model.branches["specular"](feats["specular"])
    torch.testing.assert_close(br["specular"], z)
    out = model(b)
    torch.testing.assert_close(out, (b["albedo"] + EPS) * br["diffuse"] + torch.expm1(br["specular"]))


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
