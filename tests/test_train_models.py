"""Every registered model trains on real (tiny) data with its default loss and a falling loss
(STYLE.md item 12: no model left out)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from conftest import DEVICES
from mcdenoise.models.registry import build_model, list_models
from mcdenoise.train.config import TrainConfig
from mcdenoise.train.data import batch_source
from mcdenoise.train.trainer import Trainer, data_config
from train_tiny_data import make_tiny_dataset

STEPS = 6


@pytest.fixture(autouse=True)
def one_thread():
    # Tiny tensors gain nothing from a second thread, and on a loaded 2-core machine OpenMP's
    # spin-waiting made this file 10x slower (measured: ~170 s vs ~10 s).
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny") / "data", spp=4, size=16)


@pytest.mark.parametrize("amp", ["none", "bf16"])
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", [e.name for e in list_models()])
def test_every_model_trains_with_a_falling_loss(name: str, device: str, amp: str, tiny: Path) -> None:
    """Catches a model whose default loss cannot reach its output (missing branch targets, shape
    mismatch), that gets no gradient, or that diverges at its default learning rate: STEPS
    steps on one fixed batch must lower that batch's loss. Also under bf16 autocast (``--amp
    bf16``, on the CPU since campaign 24): catches an op that refuses a bfloat16 input or a
    parameter left in bfloat16."""
    torch.manual_seed(0)
    model = build_model(name, "small").to(device)
    # A long nominal run keeps KPCN/DPCN in their per-branch phase and the lr flat for these steps.
    cfg = TrainConfig(model=name, data=str(tiny), steps=10_000, batch=2, crop=8, warmup=0, schedule="constant",
                      spp_range=(2, 4), sampling="uniform", augment=True, workers=0,
                      amp=amp).resolved(model.input_kind)
    batch = {k: v.to(device) for k, v in batch_source(tiny, model, data_config(cfg))[0].items()}
    tr = Trainer(model, cfg, torch.device(device))

    def loss_now() -> float:
        with torch.no_grad():
            return float(tr.compute_loss(batch, 0))

    before = loss_now()
    skipped = sum(tr.step(batch, t).skipped for t in range(STEPS))
    after = loss_now()
    assert skipped == 0
    assert after < before, (name, before, after)
    assert all(p.dtype == torch.float32 for p in model.parameters())


def test_bf16_on_a_cpu_without_native_bfloat16_warns(tiny: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Catches `--amp bf16` silently running emulated (several times slower than float32) on a CPU
    without AVX512-BF16/AMX, and a warning on CPUs that have it."""
    import warnings

    from mcdenoise.models import inference

    model = build_model("wskp", "small")
    cfg = TrainConfig(model="wskp", data=str(tiny), steps=10, batch=2, crop=8, workers=0, amp="bf16").resolved(model.input_kind)
    monkeypatch.setattr(inference, "native_bfloat16", lambda device="cpu": False)
    with pytest.warns(UserWarning, match="no native bfloat16"):
        Trainer(model, cfg, torch.device("cpu"))
    monkeypatch.setattr(inference, "native_bfloat16", lambda device="cpu": True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Trainer(model, cfg, torch.device("cpu"))
