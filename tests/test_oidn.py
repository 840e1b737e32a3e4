"""The OIDN 2.5.1 baseline wrapper (pyoidn): HDR is not clamped, any layout and dtype is read
correctly, shapes are checked, guides and quality are passed through, the version is reported."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from mcdenoise.eval import oidn as oidn_mod
from mcdenoise.eval.oidn import QUALITIES, OIDNError, oidn_available, oidn_denoise, version

needs_oidn = pytest.mark.skipif(not oidn_available(), reason="pyoidn (OIDN 2.5.1) not installed")


def _noisy(seed: int = 0, level: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """(clean, noisy), each (3, 48, 40) float32 HDR radiance with one vertical edge."""
    rng = np.random.default_rng(seed)
    clean = np.full((3, 48, 40), level, np.float32)
    clean[:, :, 20:] *= 0.2  # an edge, so the image is not trivially constant
    noisy = clean * rng.exponential(1.0, clean.shape).astype(np.float32)
    return clean, noisy


def _guides(shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(albedo, normal) (3, H, W) with the same edge as :func:`_noisy`, so the guides matter."""
    albedo = np.full(shape, 0.5, np.float32)
    albedo[:, :, 20:] = 0.1
    normal = np.zeros(shape, np.float32)
    normal[2] = 1.0
    return albedo, normal


#: Tolerance for comparing two OIDN runs on the same pixels, relative to the output's maximum.
#: Threaded OIDN is not promised to be bitwise repeatable (an exact comparison failed 2 of 8 full
#: suite runs with OIDN 1.4.3, issue 8). Measured with OIDN 2.5.1 (pyoidn 2.5.1.0, 2 cores, all
#: three qualities, `benchmarks/bench_oidn.py tolerance`): 20 repeated runs and runs with 1-16 threads were
#: identical, and a random walk of 1-16 ulp on every input moves the output by at most 3.4e-6 of
#: its maximum, the scale any change of summation order produces. Reading the wrong pixels (the
#: bug this guards against) moves it by 1.7-2.6x its maximum. 1e-4 sits 30x above the first and
#: 17000x below the second.
RUN_TO_RUN_RTOL = 1e-4


def _assert_same_denoise(got: np.ndarray, want: np.ndarray) -> None:
    atol = RUN_TO_RUN_RTOL * float(np.abs(want).max())
    np.testing.assert_allclose(got, want, rtol=0, atol=atol)


@needs_oidn
def test_version_is_2_5_1() -> None:
    """Catches: the baseline silently running another OIDN (an old ``oidn`` package, a system
    library shadowing the bundled one) while reports claim 2.5.1."""
    assert version() == "2.5.1"


@needs_oidn
def test_hdr_is_not_clamped_and_reduces_error() -> None:
    """Catches: the LDR default of OIDN/pyoidn (``hdr=False``) clamping radiance to [0, 1]."""
    clean, noisy = _noisy()
    out = oidn_denoise(noisy)
    assert out.shape == noisy.shape and out.dtype == np.float32 and out.flags.c_contiguous
    assert out.max() > 2.0, "HDR output was clamped to [0, 1]"
    assert np.abs(out - clean).mean() < 0.5 * np.abs(noisy - clean).mean()
    # The pitfall we guard against: LDR mode clamps.
    assert oidn_denoise(noisy, hdr=False).max() <= 1.0 + 1e-6


@needs_oidn
def test_non_contiguous_input_matches_contiguous() -> None:
    """Catches: OIDN reading a freed temporary or the wrong strides for a non-contiguous view
    (garbage output), without failing on threaded OIDN's rounding-level run-to-run noise."""
    _, noisy = _noisy(1)
    wide = np.concatenate([noisy, noisy[:, :, ::-1] * 3], axis=2)  # (3, 48, 80)
    view = wide[:, :, :40]
    assert not view.flags.c_contiguous
    want = oidn_denoise(np.ascontiguousarray(view))
    _assert_same_denoise(oidn_denoise(view), want)
    # The tolerance still sees the bug: the neighbouring pixels of the same buffer fail it.
    with pytest.raises(AssertionError):
        _assert_same_denoise(oidn_denoise(np.ascontiguousarray(wide[:, :, 40:])), want)
    # Channels-last memory seen through a (3, H, W) view (what a transpose of an EXR gives).
    hwc = np.ascontiguousarray(np.moveaxis(view, 0, -1))
    _assert_same_denoise(oidn_denoise(np.moveaxis(hwc, -1, 0)), want)


@needs_oidn
@pytest.mark.parametrize("dtype", [np.float64, np.float16, np.int32])
def test_non_float32_inputs(dtype: type) -> None:
    """Catches: float64 (numpy's default) or float16 inputs refused by pyoidn, or bytes of the
    wrong width handed to OIDN; the guides may have a dtype of their own."""
    _, noisy = _noisy(3)
    albedo, normal = _guides(noisy.shape)
    cast = noisy.astype(dtype)
    half_albedo = albedo.astype(np.float16)  # 0.1 is not exact in float16: compare like with like
    want = oidn_denoise(cast.astype(np.float32), half_albedo.astype(np.float32), normal)
    got = oidn_denoise(cast, half_albedo, normal.astype(np.float64))
    assert got.dtype == np.float32
    _assert_same_denoise(got, want)


@needs_oidn
def test_torch_tensor_input() -> None:
    """Catches: CPU tensors (what the models produce) refused or misread."""
    import torch

    _, noisy = _noisy(4)
    want = oidn_denoise(noisy)
    got = oidn_denoise(torch.from_numpy(noisy).double())
    assert isinstance(got, np.ndarray)
    _assert_same_denoise(got, want)


@needs_oidn
def test_guides_are_optional_and_used() -> None:
    """Catches: albedo/normal dropped on the way to OIDN (output identical to color-only), or a
    guide required where OIDN takes color alone."""
    clean, noisy = _noisy(2)
    albedo, normal = _guides(noisy.shape)
    alone = oidn_denoise(noisy)
    with_albedo = oidn_denoise(noisy, albedo)
    with_both = oidn_denoise(noisy, albedo, normal)
    for out in (alone, with_albedo, with_both):
        assert out.shape == noisy.shape and np.isfinite(out).all()
        assert np.abs(out - clean).mean() < 0.5 * np.abs(noisy - clean).mean()
    with pytest.raises(AssertionError):
        _assert_same_denoise(with_albedo, alone)
    with pytest.raises(AssertionError):
        _assert_same_denoise(with_both, with_albedo)


@needs_oidn
def test_quality_is_passed_through() -> None:
    """Catches: the quality argument ignored (``fast`` giving ``high``'s pixels) or an unknown
    name reaching OIDN. On the CPU device ``balanced`` equals ``high`` except with clean
    albedo+normal guides (OIDN 2.3 notes), so only ``fast`` is required to differ."""
    _, noisy = _noisy(5)
    out = {q: oidn_denoise(noisy, quality=q) for q in QUALITIES}
    assert all(np.isfinite(o).all() and o.max() > 2.0 for o in out.values())
    with pytest.raises(AssertionError):
        _assert_same_denoise(out["fast"], out["high"])
    with pytest.raises(OIDNError, match="quality 'best': expected one of high, balanced, fast"):
        oidn_denoise(noisy, quality="best")


@needs_oidn
@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((np.zeros((48, 40, 3), np.float32),), r"'color': expected \(3, H, W\), got \(48, 40, 3\)"),
        ((np.zeros((1, 3, 48, 40), np.float32),), r"'color': expected \(3, H, W\), got \(1, 3, 48, 40\)"),
        ((np.zeros((3, 0, 40), np.float32),), r"'color': empty image"),
        ((np.zeros((3, 48, 40), np.complex64),), r"'color': expected a real-valued array"),
        ((np.ones((3, 48, 40), np.float32), np.ones((3, 10, 40), np.float32)), r"'albedo': expected \(3, 48, 40\), got \(3, 10, 40\)"),
        ((np.ones((3, 48, 40), np.float32), np.ones((3, 48, 40), np.float32), np.ones((3, 48, 41), np.float32)),
         r"'normal': expected \(3, 48, 40\), got \(3, 48, 41\)"),
    ],
)
def test_bad_shapes_raise_one_line(args: tuple[np.ndarray, ...], match: str) -> None:
    """Catches: channels-last or batched arrays denoised as garbage, or mismatched guides reaching
    OIDN (pyoidn's ValueError would not name the expected shape)."""
    with pytest.raises(OIDNError, match=match) as info:
        oidn_denoise(*args)
    assert "\n" not in str(info.value)


@needs_oidn
def test_normal_without_albedo_is_refused() -> None:
    """Catches: passing normal alone, which OIDN rejects at commit with "unsupported combination
    of input features"; we say what to do instead."""
    _, noisy = _noisy(6)
    _, normal = _guides(noisy.shape)
    with pytest.raises(OIDNError, match="albedo guide to use a normal guide"):
        oidn_denoise(noisy, normal=normal)


@needs_oidn
def test_library_errors_become_one_line_oidn_errors(monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches: a failure inside OIDN escaping as pyoidn's RuntimeError, or a multi-line message
    breaking one-line logs and tables."""
    import pyoidn

    def fail(*_a: object, **_k: object) -> None:
        raise RuntimeError("OIDN filter execution failed (error 4):\nout of memory")

    monkeypatch.setattr(pyoidn, "denoise", fail)
    with pytest.raises(OIDNError, match=r"^OIDN 2\.5\.1 failed: .*\(error 4\): out of memory$"):
        oidn_denoise(_noisy()[1])


def test_missing_package_reports_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches: a missing pyoidn surfacing as a bare ImportError deep inside an evaluation, or
    oidn_available() raising instead of returning False."""
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # makes `import pyoidn` raise ImportError
    assert oidn_mod.oidn_available() is False
    with pytest.raises(OIDNError, match=r"pip install 'pyoidn==2\.5\.1\.0'"):
        oidn_denoise(_noisy()[1])


@needs_oidn
def test_threads_pin_the_device_and_keep_the_pixels() -> None:
    """Bug caught (issue 18 section 2): `eval --threads 1` limited torch to one thread while OIDN
    ran on every core, so ms/MP compared 1 core against all. ``threads=N`` must run on a device
    committed with N threads (as OIDN reports it), give the default device's pixels, with and
    without guides and at every quality, and refuse a count below 1 in one line."""
    from mcdenoise.eval.oidn import device_threads

    assert device_threads(1) == 1
    assert device_threads(2) == 2
    _, noisy = _noisy(7)
    albedo, normal = _guides(noisy.shape)
    for q in QUALITIES:
        _assert_same_denoise(oidn_denoise(noisy, albedo, normal, quality=q, threads=1),
                             oidn_denoise(noisy, albedo, normal, quality=q))
    # Guides dropped on the pinned device between calls: the albedo of the call before is not reused.
    _assert_same_denoise(oidn_denoise(noisy, threads=1), oidn_denoise(noisy))
    small = noisy[:, :17, :23]
    assert oidn_denoise(small, threads=1).shape == (3, 17, 23)
    with pytest.raises(OIDNError, match="threads must be a positive integer, got 0"):
        oidn_denoise(noisy, threads=0)


@needs_oidn
def test_prefilter_mode_is_prefiltered_guides_passed_as_clean() -> None:
    """Catches a ``prefilter`` that is ignored (the output would equal the plain run), one that
    prefilters but does not set cleanAux, or one that denoises the guides with the colour filter."""
    from mcdenoise.eval.oidn import oidn_prefilter

    clean, noisy = _noisy(4)
    rng = np.random.default_rng(5)
    albedo, normal = _guides(noisy.shape)
    albedo = (albedo * rng.uniform(0.5, 1.5, albedo.shape)).astype(np.float32)  # noisy guides
    normal = np.clip(normal + rng.normal(0, 0.3, normal.shape), -1, 1).astype(np.float32)
    got = oidn_denoise(noisy, albedo, normal, prefilter="fast", threads=1)
    al, nr = oidn_prefilter(albedo, "albedo", quality="fast", threads=1), oidn_prefilter(normal, "normal", quality="fast", threads=1)
    _assert_same_denoise(got, oidn_denoise(noisy, al, nr, clean_aux=True, threads=1))
    assert np.abs(got - oidn_denoise(noisy, albedo, normal, threads=1)).max() > 1e-3 * np.abs(got).max()
    # the prefiltered albedo is closer to the clean one than the noisy albedo was
    clean_albedo = _guides(noisy.shape)[0]
    assert np.abs(al - clean_albedo).mean() < 0.5 * np.abs(albedo - clean_albedo).mean()
    assert nr.min() >= -1 and nr.max() <= 1 and al.dtype == np.float32 and al.shape == albedo.shape


@needs_oidn
def test_prefilter_refuses_what_it_cannot_do() -> None:
    """Catches a bad guide kind or quality reaching OIDN (an opaque library error, or none)."""
    from mcdenoise.eval.oidn import oidn_prefilter

    _, noisy = _noisy(0)
    with pytest.raises(OIDNError, match="albedo or normal"):
        oidn_prefilter(noisy, "color")
    with pytest.raises(OIDNError, match="prefilter quality"):
        oidn_denoise(noisy, *_guides(noisy.shape), prefilter="best")


def test_quality_names_with_prefilter_parse_in_one_place() -> None:
    """Catches eval, bench and the OIDN method spelling ``high-pf`` differently (one of them
    passing ``high-pf`` to OIDN, or dropping the prefilter)."""
    from mcdenoise.eval.oidn import parse_quality

    assert parse_quality("high") == ("high", None) and parse_quality("fast-pf") == ("fast", "fast")
    with pytest.raises(OIDNError, match="optionally with -pf"):
        parse_quality("best-pf")
