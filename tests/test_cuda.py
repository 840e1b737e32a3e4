"""Checks that need a CUDA GPU (skipped without one; run on a lent GPU machine with
``scripts/gpu_check.sh``). Nothing in the package needs a GPU: these check that the same code
gives the CPU's results there.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from mcdenoise.cli.main import main
from mcdenoise.models import build_model, list_models, synthetic_batch
from train_tiny_data import make_tiny_dataset

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

#: Every registered model at its small preset, plus kpcn's pixel preset (window variances in float64)
#: and the combiner with its own kernel (a per-pixel gather inside the combiner).
CASES = [(e.name, "small") for e in list_models()] + [("kpcn", "pixel"), ("combine", "own")]


@pytest.mark.parametrize("name,preset", CASES, ids=[f"{n}-{p}" for n, p in CASES])
def test_cuda_forward_equals_cpu_in_float64(name: str, preset: str) -> None:
    """Catches a CUDA-only path (a fused kernel, a device-dependent branch, a tensor left on the
    CPU) that computes something other than the CPU path: same weights, same float64 batch, both
    outputs within 1e-9 relative (float64 rounding differs only in summation order)."""
    torch.manual_seed(0)
    model = build_model(name, preset).double().eval()
    batch = synthetic_batch(model, spp=2, height=21, width=27, dtype=torch.float64,
                            generator=torch.Generator().manual_seed(1))
    device = torch.device("cuda")
    with torch.no_grad():
        cpu = model(batch)
        gpu = model.to(device)({k: v.to(device) for k, v in batch.items()})
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("model,preset", [("kpcn", "pixel"), ("wskp", "small"), ("sbmc", "small"), ("layer", "small")])
def test_training_on_cuda_writes_a_run_that_loads_on_the_cpu(model: str, preset: str, tmp_path: Path) -> None:
    """Catches training that only works on the CPU (a batch or a state tensor on the wrong
    device) and CUDA checkpoints that a CPU-only machine cannot load: 4 steps on CUDA, then the run
    folder's weights denoise on the CPU."""
    data = make_tiny_dataset(tmp_path / "data")
    out = tmp_path / "run"
    rc = main(["train", "--model", model, "--preset", preset, "--data", str(data), "--out", str(out), "--steps", "4",
               "--crop", "16", "--batch", "2", "--workers", "0", "--val-every", "0", "--no-progress", "--device", "cuda"])
    assert rc == 0
    assert json.loads((out / "result.json").read_text())["device"].startswith("cuda")
    from mcdenoise.models.weights import load_denoiser

    net, info = load_denoiser(out, device="cpu")
    assert next(net.parameters()).device.type == "cpu" and info["preset"] == preset
