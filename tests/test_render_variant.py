"""Mitsuba variant choice: CUDA where a GPU is present, LLVM otherwise, `--variant` overrides."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.data.format import read_image
from mcdenoise.errors import SceneError
from mcdenoise.render import _mitsuba as M


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    monkeypatch.delenv("MCDENOISE_VARIANT", raising=False)
    return monkeypatch


def test_auto_picks_cuda_only_with_a_gpu_and_a_cuda_build(no_env: pytest.MonkeyPatch) -> None:
    """Catches: auto selection ignoring the GPU, or picking CUDA on a machine (or build) without it."""
    no_env.setattr(M, "_built_variants", lambda: ["scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb"])
    no_env.setattr(M, "cuda_available", lambda: True)
    assert M.select_variant(None) == "cuda_ad_rgb"
    assert M.select_variant("auto") == "cuda_ad_rgb"
    assert M.select_variant("llvm_ad_rgb") == "llvm_ad_rgb"  # an explicit choice wins
    no_env.setattr(M, "cuda_available", lambda: False)
    assert M.select_variant("auto") == "llvm_ad_rgb"
    no_env.setattr(M, "cuda_available", lambda: True)
    no_env.setattr(M, "_built_variants", lambda: ["scalar_rgb", "llvm_ad_rgb"])
    assert M.select_variant("auto") == "llvm_ad_rgb"


def test_environment_and_bad_names(no_env: pytest.MonkeyPatch) -> None:
    """Catches: MCDENOISE_VARIANT ignored, or a scalar variant (which our JIT renderer cannot use)
    accepted."""
    no_env.setattr(M, "cuda_available", lambda: True)
    no_env.setattr(M, "_built_variants", lambda: ["llvm_ad_rgb", "cuda_ad_rgb"])
    no_env.setenv("MCDENOISE_VARIANT", "llvm_ad_rgb")
    assert M.select_variant(None) == "llvm_ad_rgb"
    assert M.select_variant("cuda_ad_rgb") == "cuda_ad_rgb"
    with pytest.raises(SceneError, match="scalar_rgb"):
        M.select_variant("scalar_rgb")
    no_env.setenv("MCDENOISE_VARIANT", "bogus")
    with pytest.raises(SceneError, match="bogus"):
        M.select_variant(None)


def test_cuda_available_without_driver(monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches: the driver probe raising instead of answering False when libcuda is missing."""
    def no_lib(name: str) -> None:
        raise OSError(f"{name}: cannot open shared object file")

    monkeypatch.setattr(M.ctypes, "CDLL", no_lib)
    assert M.cuda_available() is False


@pytest.mark.render
def test_variant_cannot_change_after_first_render(no_env: pytest.MonkeyPatch) -> None:
    """Catches: a silent variant switch after the integrator class was built for the old one."""
    M.mitsuba()
    other = "cuda_ad_rgb" if M.VARIANT == "llvm_ad_rgb" else "llvm_ad_rgb"
    assert M.active_variant() == M.VARIANT
    with pytest.raises(SceneError, match="already in use"):
        M.set_variant(other)
    assert M.set_variant(M.VARIANT) == M.VARIANT


@pytest.mark.render
@pytest.mark.skipif(not M.cuda_available() or "cuda_ad_rgb" not in M._built_variants(),
                    reason="needs an NVIDIA GPU and a Mitsuba build with cuda_ad_rgb")
def test_dataset_on_gpu(tmp_path: Path) -> None:
    """Catches: the CUDA render path failing (host copies, kernels) where a GPU is present: a tiny
    dataset rendered with the automatic choice uses cuda_ad_rgb and gives finite images."""
    root = tmp_path / "gpu"
    env = {k: v for k, v in os.environ.items() if k != "MCDENOISE_VARIANT"}
    cmd = [sys.executable, "-m", "mcdenoise.cli.main", "dataset", "--count", "1", "--views", "2", "--out", str(root),
           "--spp", "2", "--ref-spp", "16", "--size", "16", "--objects", "10-12", "--no-progress"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    for v in range(2):
        img = read_image(root / "proc_000000" / f"view_{v:03d}")
        assert "cuda_ad_rgb" in img.meta.renderer
        assert np.isfinite(img.read_noisy(["radiance"])["radiance"]).all()
    assert json.loads((root / "dataset.json").read_text())["views"] == 2
    # Issue 18: the variant is recorded, and a model card's dataset command states it.
    assert json.loads((root / "dataset.json").read_text())["variant"] == "cuda_ad_rgb"
    from mcdenoise.models.ship import dataset_command

    assert "--variant cuda_ad_rgb" in dataset_command(root)
