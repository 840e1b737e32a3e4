"""SBMC Fig. 4 toy experiment: data, equal capacity, kernel semantics, a few training steps, CLI."""

from __future__ import annotations

import json

import torch

from mcdenoise.cli.main import main
from mcdenoise.repro.splat_vs_gather import (
    ToyConfig,
    ToyKernelNet,
    _gaussian_target,
    count_parameters,
    make_batch,
    run_experiment,
)


def test_equal_capacity() -> None:
    g, s = ToyKernelNet("gather"), ToyKernelNet("splat")
    assert count_parameters(g) == count_parameters(s) > 10_000


def test_batch_has_outliers_and_blurred_target() -> None:
    cfg = ToyConfig(size=32, outlier_prob=0.05)
    noisy, target = make_batch(cfg, 4, torch.Generator().manual_seed(0))
    assert noisy.shape == target.shape == (4, 3, 32, 32)
    frac = float((noisy > 5).any(dim=1).float().mean())
    assert 0.02 < frac < 0.09  # about outlier_prob of the samples are outliers
    assert float(target.max()) <= 1.0 + 1e-6 and float(target.min()) >= -1e-6
    # The Gaussian target is smoother than the texture: lower total variation.
    clean, _ = make_batch(ToyConfig(size=32, outlier_prob=0.0), 4, torch.Generator().manual_seed(0))
    tv = lambda x: float((x[..., 1:] - x[..., :-1]).abs().mean())  # noqa: E731
    assert tv(_gaussian_target(clean, 1.5, 9)) < tv(clean)


def test_centre_kernels_copy_the_input_for_both_modes() -> None:
    """Same logits -> same operator for a centre-only kernel: gather and splat both return x."""
    x = torch.rand(2, 3, 10, 11) + 0.1
    for mode in ("gather", "splat"):
        net = ToyKernelNet(mode, kernel_size=5)
        with torch.no_grad():
            net.head.weight.zero_()
            net.head.bias.fill_(-1e4)
            net.head.bias[12] = 0.0
            assert torch.allclose(net(x), x, rtol=1e-6)


def test_a_few_training_steps_run_and_write_json(tmp_path) -> None:
    cfg = ToyConfig(steps=6, batch=2, size=16, test_textures=2, lr=3e-3)
    res = run_experiment(cfg, log=lambda s: None)
    assert res["parameters"]["gather"] == res["parameters"]["splat"]
    for m in ("gather", "splat"):
        c = res["curves"][m]
        assert len(c) == 6 and all(v == v and v >= 0 for v in c)
        assert res["test_loss"][m] >= 0
    rc = main(["repro", "splat-vs-gather", "--steps", "2", "--batch", "1", "--out", str(tmp_path), "--quiet"])
    assert rc == 0
    data = json.loads((tmp_path / "splat_vs_gather.json").read_text())
    assert set(data["curves"]) == {"gather", "splat"} and len(data["curves"]["splat"]) == 2
