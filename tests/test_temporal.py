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


#: A long history: n is capped at 1 / alpha = 5, so the blend weight is alpha = 0.2.
LONG = 5.0


def _ones_n(like: torch.Tensor, value: float = LONG) -> torch.Tensor:
    return torch.full_like(like[:, :1], value)


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
    out, length = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, _ones_n(cur), alpha=0.2)
    expected = 0.2 * cur[..., 1:, 2:] + 0.8 * prev[..., :-1, :-2]
    torch.testing.assert_close(length[..., 1:, 2:], _ones_n(cur)[..., 1:, 2:], rtol=0, atol=0)
    assert (length[..., :1, :] == 1).all() and (length[..., :, :2] == 1).all()
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
    out, length = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, _ones_n(cur))
    assert (length[..., 3:6, 4:7] == 1).all() and (length[..., 6:8, 8:10] == 1).all()
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
    hist = torch.randint(0, 8, (b, 1, h, w), generator=g).to(DT)  # short and capped histories
    fast, n_fast = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, hist, alpha=0.2)
    ref, n_ref = temporal_accumulate_reference(cur, prev, motion, pos, ppos, n, pn, hist, alpha=0.2)
    torch.testing.assert_close(fast, ref, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(n_fast, n_ref, rtol=1e-12, atol=1e-12)
    assert n_fast.min() >= 1 and n_fast.max() <= 5
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
        return temporal_accumulate(c, p, m, pos, ppos, n, pn, length, alpha=0.2)[0]

    length = torch.tensor([[1.0, 2.0, 3.0, 4.0, 9.0]], dtype=DT).expand(h, w)[None, None]

    assert torch.autograd.gradcheck(f, (cur, prev, motion), eps=1e-6, atol=1e-8)


def test_alpha_one_is_identity() -> None:
    cur, prev, motion, pos, ppos, n, pn = _translation()
    out, length = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, _ones_n(cur), alpha=1.0)
    torch.testing.assert_close(out, cur)
    assert (length == 1).all()


def test_first_frame_is_its_own_input() -> None:
    """Issue 8 item 9: with a fixed alpha the first blended frame was 0.2 x itself + 0.8 x whatever
    came before. A pixel without history (n_prev = 0) must come out as its input, with n = 1."""
    cur, prev, motion, pos, ppos, n, pn = _translation()
    out, length = temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, _ones_n(cur, 0.0))
    torch.testing.assert_close(out, cur, rtol=0, atol=0)
    assert (length == 1).all()


def _static_sequence(frames: int, h: int = 6, w: int = 7) -> list[torch.Tensor]:
    g = torch.Generator().manual_seed(7)
    return [torch.rand(1, 3, h, w, generator=g, dtype=DT) for _ in range(frames)]


def test_static_sequence_is_running_mean_then_ema() -> None:
    """Frame 1 is its input, frames 2..5 (1 / alpha) the running mean of all frames so far, later
    frames an exponential moving average with weight alpha. Catches a fixed alpha from the start
    (frame 2 would be 0.2 x frame 2 + 0.8 x frame 1) and a history length that is not reprojected
    or not incremented."""
    frames = _static_sequence(8)
    h, w = frames[0].shape[-2:]
    pos, nrm = _plane(h, w, (0.0, 0.0))
    motion = torch.zeros(1, 2, h, w, dtype=DT)
    acc = TemporalAccumulation(alpha=0.2)
    ema = None
    for t, frame in enumerate(frames, start=1):
        out = acc(frame, motion, pos, nrm)
        if t <= 5:
            torch.testing.assert_close(out, torch.stack(frames[:t]).mean(0), rtol=1e-12, atol=1e-12)
            assert (acc.history_length == t).all()
            ema = out
        else:
            ema = 0.2 * frame + 0.8 * ema
            torch.testing.assert_close(out, ema, rtol=1e-12, atol=1e-12)
            assert (acc.history_length == 5).all()
    acc.reset()
    torch.testing.assert_close(acc(frames[0], motion, pos, nrm), frames[0], rtol=0, atol=0)


def test_disocclusion_restarts_the_history() -> None:
    """A pixel rejected by the geometry test starts again at n = 1 and its next frame is the mean
    of two, while its neighbours continue their long history."""
    frames = _static_sequence(7)
    h, w = frames[0].shape[-2:]
    pos, nrm = _plane(h, w, (0.0, 0.0))
    moved = pos.clone()
    moved[..., 2, 3] += torch.tensor([0.0, 0.0, 4.0], dtype=DT)  # something appears at (2, 3)
    motion = torch.zeros(1, 2, h, w, dtype=DT)
    acc = TemporalAccumulation(alpha=0.2)
    for t in range(6):
        acc(frames[t], motion, pos, nrm)
    out = acc(frames[6], motion, moved, nrm)
    assert acc.history_length[0, 0, 2, 3] == 1 and acc.history_length[0, 0, 0, 0] == 5
    torch.testing.assert_close(out[..., 2, 3], frames[6][..., 2, 3], rtol=0, atol=0)
    out2 = acc(frames[0], motion, moved, nrm)
    torch.testing.assert_close(out2[..., 2, 3], (frames[6][..., 2, 3] + frames[0][..., 2, 3]) / 2)


def test_bad_input_raises() -> None:
    cur, prev, motion, pos, ppos, n, pn = _translation()
    with pytest.raises(ValueError, match="motion"):
        temporal_accumulate(cur, prev, motion[:, :1], pos, ppos, n, pn, _ones_n(cur))
    with pytest.raises(ValueError, match="previous"):
        temporal_accumulate(cur, prev[..., :-1], motion, pos, ppos, n, pn, _ones_n(cur))
    with pytest.raises(ValueError, match="history_length"):
        temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, cur)
    with pytest.raises(ValueError, match="alpha"):
        temporal_accumulate(cur, prev, motion, pos, ppos, n, pn, _ones_n(cur), alpha=1.5)
