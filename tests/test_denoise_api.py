"""`mcdenoise.denoise`: numpy/torch round trips, model choice, and the documented example (issue 11, item 2)."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

import mcdenoise
from mcdenoise.infer.choose import card_relmse
from mcdenoise.infer.sources import InputError, NonFiniteInputWarning
from mcdenoise.models import build_model
from mcdenoise.models import weights as weights_mod

ROOT = Path(__file__).resolve().parents[1]
H, W = 24, 30


def _buffers(seed: int = 0) -> dict[str, np.ndarray]:
    """Channel-first float64 buffers."""
    rng = np.random.default_rng(seed)
    return {
        "color": rng.random((3, H, W)) * 2,
        "albedo": rng.random((3, H, W)),
        "normal": rng.random((3, H, W)) * 2 - 1,
        "depth": rng.random((H, W)) * 5,
    }


@pytest.fixture(scope="module")
def wskp():
    torch.manual_seed(0)
    return build_model("wskp", "small").eval()


def _reference(model, b) -> np.ndarray:
    batch = {"radiance": b["color"], "albedo": b["albedo"], "normal": b["normal"], "depth": b["depth"][None]}
    with torch.no_grad():
        return model({k: torch.from_numpy(np.ascontiguousarray(v, np.float32))[None] for k, v in batch.items()})[0].numpy()


def test_numpy_float64_noncontiguous_channel_last(wskp):
    """Catches strides or the (H, W, 3) layout being misread, and the dtype or layout not coming back."""
    b = _buffers()
    # Channel-last views with negative and doubled strides.
    big = {k: np.repeat(np.moveaxis(v, 0, -1) if v.ndim == 3 else v, 2, axis=1)[:, ::2] for k, v in b.items()}
    color = np.ascontiguousarray(big["color"][::-1])[::-1]  # same values, negative row stride
    assert not color.flags.c_contiguous and color.dtype == np.float64
    out = mcdenoise.denoise(color, big["albedo"], big["normal"], big["depth"], model=wskp, device="cpu")
    assert isinstance(out, np.ndarray) and out.dtype == np.float64 and out.shape == (H, W, 3)
    np.testing.assert_allclose(np.moveaxis(out, -1, 0), _reference(wskp, b), rtol=1e-5, atol=1e-6)


def test_torch_float16_round_trip(wskp):
    """Catches a float16 tensor coming back as float32 or numpy, or half precision inside the model."""
    b = _buffers()
    t = {k: torch.from_numpy(v).to(torch.float16) for k, v in b.items()}
    out = mcdenoise.denoise(t["color"], t["albedo"], t["normal"], t["depth"], model=wskp, device="cpu")
    assert isinstance(out, torch.Tensor) and out.dtype == torch.float16 and out.shape == (3, H, W)
    half = {k: v.to(torch.float16).double().numpy() for k, v in t.items()}
    np.testing.assert_allclose(out.double().numpy(), _reference(wskp, half), rtol=2e-3, atol=2e-3)


def test_missing_channel_is_named(wskp):
    """Catches a model run without one of its inputs."""
    b = _buffers()
    with pytest.raises(InputError, match="depth"):
        mcdenoise.denoise(b["color"], b["albedo"], b["normal"], model=wskp)


def test_nonfinite_warning_gives_count(wskp):
    """Catches NaN/Inf reaching the model, or a warning that does not say how many."""
    b = _buffers()
    b["color"][0, :2, :3] = np.nan
    b["depth"][0, 0] = np.inf
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = mcdenoise.denoise(b["color"], b["albedo"], b["normal"], b["depth"], model=wskp, device="cpu")
    assert np.isfinite(out).all()
    msgs = [str(w.message) for w in caught if issubclass(w.category, NonFiniteInputWarning)]
    assert len(msgs) == 1 and "7 non-finite" in msgs[0]


def test_card_relmse_forms():
    """Catches model cards whose relMSE is stored per spp being ranked as if they had none."""
    assert card_relmse({"test": {"relMSE": 0.05}}) == 0.05
    assert card_relmse({"test": {"relmse": {"4spp": 0.2, "8spp": 0.1, "32spp": 0.02}}}) == 0.1
    assert card_relmse({"test": {"relmse_by_spp": {"16": 0.3, "4": 0.5}}}) == 0.5
    assert card_relmse({"test": {"psnr": 30}}) is None and card_relmse({}) is None
    # The card mcdenoise.models.ship writes: the model's row of the "all" subset, at 8 spp.
    shipped_card = {"test": {"subsets": {
        "dof_motion": {"8": {"model": {"relmse": 0.9}}},
        "all": {"4": {"model": {"relmse": 0.4}, "noisy": {"relmse": 2.0}},
                "8": {"model": {"relmse": 0.3}, "noisy": {"relmse": 1.0}}},
    }}}
    assert card_relmse(shipped_card) == 0.3


@pytest.fixture
def fake_shipped(tmp_path, monkeypatch):
    """Shipped weights stood in by random ones: wskp (relMSE 0.2) and wskp_mr (relMSE 0.1), on the
    procedural test split and on the third-party validation scenes, where OIDN scores 0.15."""
    entries = []
    for name, rel in (("wskp", 0.2), ("wskp_mr", 0.1)):
        torch.manual_seed(0)
        path = tmp_path / f"{name}-small.safetensors"
        save_file(build_model(name, "small").state_dict(), str(path), metadata={"model": name, "preset": "small"})
        card = {"test": {"relmse": {"8": rel}}, "inputs": ["radiance", "albedo", "normal", "depth"],
                "validation": {"spp": {"8": {"model": {"relmse": rel}, "oidn-high": {"relmse": 0.15}}}}}
        path.with_suffix(".json").write_text(json.dumps(card))
        entries.append(weights_mod.ShippedWeights(name, "small", path, card))
    monkeypatch.setattr(weights_mod, "shipped", lambda: list(entries))
    return entries


def test_without_model_the_lowest_relmse_wins(fake_shipped, caplog):
    """Catches model=None picking by name or order instead of the cards' validation relMSE."""
    b = _buffers()
    with caplog.at_level("INFO", logger="mcdenoise.denoise"):
        mcdenoise.denoise(b["color"], b["albedo"], b["normal"], b["depth"], device="cpu")
    assert "wskp_mr" in caplog.text and "validation relMSE" in caplog.text


def test_without_model_missing_inputs_fall_back_to_oidn(fake_shipped, caplog):
    """Catches a refusal where OIDN could denoise: without depth no shipped model runs, OIDN does."""
    b = _buffers()
    with caplog.at_level("INFO", logger="mcdenoise.denoise"):
        out = mcdenoise.denoise(b["color"], b["albedo"], b["normal"])
    assert out.shape == b["color"].shape and "oidn" in caplog.text


def test_without_model_or_oidn_missing_inputs_are_named(fake_shipped, monkeypatch):
    """Catches a refusal that does not say which channel the shipped models need (OIDN absent)."""
    import mcdenoise.eval.oidn as oidn_mod

    monkeypatch.setattr(oidn_mod, "oidn_available", lambda: False)
    b = _buffers()
    with pytest.raises(InputError, match="depth"):
        mcdenoise.denoise(b["color"], b["albedo"], b["normal"])


def test_documented_example_runs(monkeypatch, tmp_path):
    """Catches docs/DENOISE.md's Python example going stale. It runs on the real shipped weights
    when they exist; before they do, on random stand-ins registered as shipped."""
    text = (ROOT / "docs" / "DENOISE.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert blocks, "docs/DENOISE.md has no python example"
    if not any(s.name in ("wskp", "wskp_mr") for s in weights_mod.shipped()):
        torch.manual_seed(0)
        path = tmp_path / "wskp-small.safetensors"
        save_file(build_model("wskp", "small").state_dict(), str(path), metadata={"model": "wskp", "preset": "small"})
        monkeypatch.setattr(weights_mod, "shipped", lambda: [weights_mod.ShippedWeights("wskp", "small", path, {})])
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(blocks[0], "docs/DENOISE.md", "exec"), namespace)
    assert namespace["clean"].shape == namespace["color"].shape


def test_the_fast_finite_check_counts_exactly() -> None:
    """Catches the one-pass finite check (a sum) missing a NaN or Inf, or reporting values as
    non-finite when only the sum overflowed (3e38 x 16 is Inf in float32)."""
    from mcdenoise.infer.sources import _sanitize

    big = np.full((3, 4, 4), 3e38, np.float32)
    out, n = _sanitize(big)
    assert n == 0 and np.array_equal(out, big)
    bad = np.ones((3, 4, 4), np.float32)
    bad[0, 1, 1], bad[2, 3, 0], bad[1, 0, 2] = np.nan, np.inf, -np.inf
    out, n = _sanitize(bad)
    assert n == 3 and np.isfinite(out).all() and out[0, 1, 1] == 0


def test_repeated_calls_reuse_the_prepared_model_until_the_weights_change(tmp_path) -> None:
    """Catches two bugs: every call loading and folding the weights again (~15 ms, 10% of wskp's
    1080p time, issue 18), and a cache that serves stale weights after the file is rewritten."""
    from mcdenoise.infer.choose import choose_model
    from mcdenoise.infer.sources import from_arrays

    b = _buffers()
    inputs = from_arrays(np.asarray(b["color"], np.float32), albedo=np.asarray(b["albedo"], np.float32),
                         normal=np.asarray(b["normal"], np.float32), depth=np.asarray(b["depth"], np.float32))
    path = tmp_path / "w.safetensors"
    for seed in (0, 1):
        torch.manual_seed(seed)
        save_file(build_model("wskp", "small").state_dict(), str(path), metadata={"model": "wskp", "preset": "small"})
        first, _ = choose_model(inputs, str(path), precision="float32")
        again, info = choose_model(inputs, str(path), precision="float32")
        assert again is first and info["why"] == "as asked"
        if seed == 0:
            before = first
    assert first is not before
    w0 = next(before.parameters())
    assert not torch.equal(w0, next(first.parameters()))
    other, _ = choose_model(inputs, str(path), precision="bfloat16")
    assert other is not first  # a precision is part of what was prepared


def test_self_ensemble_is_the_median_of_the_turned_runs(wskp):
    """Catches ``self_ensemble=True`` not reaching the run (one pass) or a pixel model's turned
    inputs mangled (normals, depth and albedo move with the colour): the result equals the
    per-pixel median of the model run on each turned image and turned back, on a non-square image."""
    from mcdenoise.models.symmetry import ALL_OPS, median_of, transform_batch, untransform

    b = _buffers()
    out = mcdenoise.denoise(b["color"], b["albedo"], b["normal"], b["depth"], model=wskp, device="cpu",
                            self_ensemble=True)
    batch = {"radiance": b["color"], "albedo": b["albedo"], "normal": b["normal"], "depth": b["depth"][None]}
    batch = {k: torch.from_numpy(np.ascontiguousarray(v, np.float32))[None] for k, v in batch.items()}
    with torch.no_grad():
        want = median_of([untransform(wskp(transform_batch(batch, op))[0].numpy(), op) for op in ALL_OPS])
    np.testing.assert_allclose(out, want, rtol=1e-5, atol=1e-6)
    assert np.abs(want - _reference(wskp, b)).max() > 1e-3
