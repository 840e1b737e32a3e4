"""Temporal accumulation (WSKP Sec. 4.1): reprojection, rejection, blend; fast vs reference."""

from __future__ import annotations

import pytest
import torch

from mcdenoise.ops.temporal import TemporalAccumulation, reproject, temporal_accumulate, temporal_accumulate_reference

DT = torch.float64


def _plane(h: int, w: int, shift: tuple[float, float], scale: float = 0.01) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions/normals of a plane z=0 seen by a camera translated by ``shift`` pixels."""
    ys, xs = torch.meshgrid(torch.arange(h, dtype=DT), torch.arange(w, dtype=DT), indexing="ij")
    pos = torch.stack([(xs - shift[0]) * scale, (ys - shift[1]) * scale, torch.zeros_like(xs)])[None]
    n = torch.zeros(1, 3, h, w, dtype=DT)
    n[:, 2] = 1
    return pos, n


def _translation(h: int = 9, w: int = 11, m: tuple[float, float] = (2.0, 1.0)):
    g = torch.Generator().manual_seed(1)
    prev = torch.rand(1, 3, h, w, generator=g, dtype=DT)
    cur = torch.rand(1, 3, h, w, generator=g, dtype=DT)
    motion = torch.empty(1, 2, h, w, dtype=DT)
    motion[:, 0], motion[:, 1] = m
    pos_prev, n = _plane(h, w, (0.0, 0.0))
    pos_cur, _ = _plane(h, w, m)
    return cur, prev, motion, pos_cur, pos_prev, n, n.clone()


def test_integer_translation_exact_interior_and_border_rejected() -> None:
    cur, prev, motion, pos, ppos, n, pn = _translation()
    out = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, alpha=0.2)
    expected = 0.2 * cur[..., 1:, 2:] + 0.8 * prev[..., :-1, :-2]
    torch.testing.assert_close(out[..., 1:, 2:], expected, rtol=0, atol=1e-12)
    # Pixels whose source lies outside the previous frame keep the current value.
    torch.testing.assert_close(out[..., :1, :], cur[..., :1, :], rtol=0, atol=0)
    torch.testing.assert_close(out[..., :, :2], cur[..., :, :2], rtol=0, atol=0)


def test_fractional_motion_reproduces_linear_image() -> None:
    h, w, m = 8, 10, (0.5, 0.25)
    cur, _, motion, pos, ppos, n, pn = _translation(h, w, m)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=DT), torch.arange(w, dtype=DT), indexing="ij")
    prev = torch.stack([0.3 * xs + 0.1 * ys, 2.0 - 0.05 * xs, 0.2 * ys])[None]
    hist, valid = reproject(prev, motion, pos, ppos, n, pn)
    want = torch.stack([0.3 * (xs - 0.5) + 0.1 * (ys - 0.25), 2.0 - 0.05 * (xs - 0.5), 0.2 * (ys - 0.25)])[None]
    assert valid[..., 1:, 1:].all()
    torch.testing.assert_close(hist[..., 1:, 1:], want[..., 1:, 1:], rtol=0, atol=1e-12)


def test_disocclusion_rejected_by_position_and_normal() -> None:
    cur, prev, motion, pos, ppos, n, pn = _translation()
    # A box appears in the current frame at 4 world units in front of the plane: positions disagree.
    pos[..., 3:6, 4:7] += torch.tensor([0.0, 0.0, 4.0], dtype=DT).view(1, 3, 1, 1)
    # Elsewhere the normal turned by 90 degrees while the position still matches.
    n = n.clone()
    n[..., 6:8, 8:10] = torch.tensor([1.0, 0.0, 0.0], dtype=DT).view(1, 3, 1, 1)
    out = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn)
    torch.testing.assert_close(out[..., 3:6, 4:7], cur[..., 3:6, 4:7], rtol=0, atol=0)
    torch.testing.assert_close(out[..., 6:8, 8:10], cur[..., 6:8, 8:10], rtol=0, atol=0)
    # A pixel outside both regions is still blended.
    torch.testing.assert_close(out[..., 2, 3], 0.2 * cur[..., 2, 3] + 0.8 * prev[..., 1, 1])


def test_fast_matches_reference_random_rejections() -> None:
    g = torch.Generator().manual_seed(3)
    b, c, h, w = 2, 3, 5, 6
    cur = torch.rand(b, c, h, w, generator=g, dtype=DT)
    prev = torch.rand(b, c, h, w, generator=g, dtype=DT)
    motion = (torch.rand(b, 2, h, w, generator=g, dtype=DT) - 0.5) * 3
    pos = torch.rand(b, 3, h, w, generator=g, dtype=DT) * 0.1
    ppos = pos + (torch.rand(b, 3, h, w, generator=g, dtype=DT) - 0.5) * 0.06
    n = torch.nn.functional.normalize(torch.rand(b, 3, h, w, generator=g, dtype=DT) + 0.5, dim=1)
    pn = torch.nn.functional.normalize(n + (torch.rand(b, 3, h, w, generator=g, dtype=DT) - 0.5) * 0.8, dim=1)
    n[0, :, 0, 0] = 0  # a miss against a hit: rejected
    n[1, :, 2, :] = 0
    pn[1, :, 1:4, :] = 0  # misses on both sides: blended
    fast = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, alpha=0.2)
    ref = temporal_accumulate_reference(cur, prev, motion, pos, ppos, n, pn, alpha=0.2)
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    _, valid = reproject(prev, motion, pos, ppos, n, pn)
    assert 0 < valid.sum() < valid.numel(), "the random case should mix kept and rejected pixels"


def test_gradcheck() -> None:
    g = torch.Generator().manual_seed(4)
    h, w = 4, 5
    cur, prev, motion, pos, ppos, n, pn = _translation(h, w, (0.3, 0.6))
    cur = torch.rand(1, 2, h, w, generator=g, dtype=DT, requires_grad=True)
    prev = torch.rand(1, 2, h, w, generator=g, dtype=DT, requires_grad=True)
    # Fractional parts stay away from 0 and 1, where the bilinear weights have kinks.
    motion = (motion + 0.05 * torch.rand(1, 2, h, w, generator=g, dtype=DT)).requires_grad_(True)

    def f(c: torch.Tensor, p: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        return temporal_accumulate(c, p, m, pos, ppos, n, pn, alpha=0.2)

    assert torch.autograd.gradcheck(f, (cur, prev, motion), eps=1e-6, atol=1e-8)


def test_alpha_one_is_identity_and_module() -> None:
    cur, prev, motion, pos, ppos, n, pn = _translation()
    torch.testing.assert_close(temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, alpha=1.0), cur)
    mod = TemporalAccumulation(alpha=0.2)
    torch.testing.assert_close(mod(cur, prev, motion, pos, ppos, n, pn), temporal_accumulate(cur, prev, motion, pos, ppos, n, pn))


def test_bad_input_raises() -> None:
    cur, prev, motion, pos, ppos, n, pn = _translation()
    with pytest.raises(ValueError, match="motion"):
        temporal_accumulate(cur, prev, motion[:, :1], pos, ppos, n, pn)
    with pytest.raises(ValueError, match="previous"):
        temporal_accumulate(cur, prev[..., :-1], motion, pos, ppos, n, pn)
    with pytest.raises(ValueError, match="alpha"):
        temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, alpha=1.5)
