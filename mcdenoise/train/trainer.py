"""One optimizer step for any registered model: the phase's loss, the guarded update, validation.

No files and no process group handling: :mod:`mcdenoise.train.loop` owns the run folder and
``torchrun``; this module is what tests, benchmarks and notebooks drive directly.
"""

from __future__ import annotations

import warnings
from contextlib import nullcontext
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

from mcdenoise.models.registry import Denoiser
from mcdenoise.train.config import ConfigError, TrainConfig
from mcdenoise.train.data import DataConfig
from mcdenoise.train.losses import get_loss, input_guide
from mcdenoise.train.optim import StepOutcome, apply_gradients, build_optimizer, lr_at
from mcdenoise.train.runlog import VAL_METRICS

__all__ = ["Trainer", "data_config", "has_branches"]


class _Objective(nn.Module):
    """Wraps a model so that DistributedDataParallel sees whichever forward the phase needs.

    Calling ``model.forward_branches`` directly on a DDP-wrapped model would skip DDP's gradient
    hooks; routing both phases through this module's ``forward`` keeps them synchronised.
    """

    def __init__(self, model: Denoiser) -> None:
        super().__init__()
        self.model = model

    def forward(self, batch: dict[str, torch.Tensor], branches: bool) -> dict[str, torch.Tensor]:
        if branches:
            return self.model.forward_branches(batch)  # type: ignore[operator]
        if hasattr(self.model, "forward_aux"):  # the image and outputs with loss terms of their own
            return self.model.forward_aux(batch)  # type: ignore[operator]
        return {"image": self.model(batch)}


def has_branches(model: Denoiser) -> bool:
    """True for models trained per branch first (KPCN/DPCN): they expose both halves of Eq. 4."""
    return hasattr(model, "forward_branches") and hasattr(model, "branch_targets")


def data_config(cfg: TrainConfig) -> DataConfig:
    """The data side's settings for this run."""
    return DataConfig(crop=cfg.crop, batch=cfg.batch, spp_range=cfg.spp_range, sampling=cfg.sampling, augment=cfg.augment,
                      exposure=cfg.exposure, workers=cfg.workers, target=cfg.target, seed=cfg.seed)


class Trainer:
    """Model, optimizer and the guarded step; no files (the caller owns the run folder).

    Args:
        model: a registered model on ``device``.
        cfg: a resolved :class:`TrainConfig`.
        distributed: wrap in DistributedDataParallel (the process group must exist).
    """

    def __init__(self, model: Denoiser, cfg: TrainConfig, device: torch.device, distributed: bool = False) -> None:
        self.model, self.cfg, self.device = model, cfg, device
        if cfg.amp == "bf16" and device.type == "cpu":
            from mcdenoise.models.inference import native_bfloat16

            if not native_bfloat16("cpu"):
                warnings.warn("--amp bf16: this CPU has no native bfloat16 (AVX512-BF16/AMX); emulated, it is "
                              "slower than float32", stacklevel=2)
        self.loss = get_loss(cfg.loss or "l1")
        if distributed and device.type == "cuda":
            # BatchNorm (WSKP's RepVGG blocks) would otherwise normalise by per-rank statistics;
            # SyncBatchNorm exists only on GPUs, so CPU ranks keep per-rank statistics (docs say so).
            nn.SyncBatchNorm.convert_sync_batchnorm(model)
        self.objective: nn.Module = _Objective(model)
        if distributed:
            self.objective = nn.parallel.DistributedDataParallel(
                self.objective, device_ids=[device.index] if device.type == "cuda" else None
            )
        self.optimizer = build_optimizer(model, cfg)
        self.params = [p for p in model.parameters() if p.requires_grad]
        self.branch_steps = int(round((cfg.branch_fraction or 0.0) * cfg.steps)) if has_branches(model) else 0
        if self.loss.guided and (self.branch_steps or "radiance" not in model.required_channels()):
            # The guide is a radiance estimate: it matches neither KPCN's branch domains nor a model
            # that never reads radiance.
            raise ConfigError(f"loss {self.loss.name!r} is weighted by the noisy radiance: it needs a model that reads "
                             "'radiance' and no per-branch phase (branch_fraction 0)")
        self.distributed = distributed
        self._buffers_to_guard = list(model.buffers())

    def phase(self, step: int) -> str:
        return "branches" if step < self.branch_steps else "image"

    def compute_loss(self, batch: dict[str, torch.Tensor], step: int) -> torch.Tensor:
        """The scalar loss of ``batch`` for the phase of ``step`` (graph kept for backward)."""
        branches = self.phase(step) == "branches"
        amp = self.cfg.amp == "bf16" and self.device.type in ("cuda", "cpu")
        ctx = torch.autocast(self.device.type, dtype=torch.bfloat16) if amp else nullcontext()
        with ctx:
            out = self.objective(batch, branches)
        if not branches:
            guide = input_guide(batch["radiance"]) if self.loss.guided else None
            loss = self.loss(out["image"].float(), batch["target"], guide)
            if len(out) > 1:  # forward_aux's extra outputs, each weighted as the model says
                weights = self.model.aux_loss_weights()  # type: ignore[operator]
                loss = loss + sum(weights[n] * self.loss(out[n].float(), batch["target"], guide)
                                  for n in sorted(out) if n != "image")
            return loss
        ref = {"radiance": batch["target"]}
        ref.update({k.split(":", 1)[1]: v for k, v in batch.items() if k.startswith("target:")})
        targets = self.model.branch_targets(ref, batch)  # type: ignore[operator]
        # Sum, not mean: each branch gets the gradient it would get if trained alone (Sec. 4.3).
        return sum(self.loss(out[n].float(), targets[n]) for n in sorted(targets))  # type: ignore[return-value]

    def step(self, batch: dict[str, torch.Tensor], step: int) -> StepOutcome:
        """One optimizer step on ``batch`` at schedule position ``step`` (0-based)."""
        for g in self.optimizer.param_groups:
            g["lr"] = lr_at(step, self.cfg)
        self.model.train()
        # BatchNorm running statistics update in the forward pass: a non-finite batch would poison
        # them even though the optimizer step is skipped, so keep a copy to restore (they are small).
        saved = [b.detach().clone() for b in self._buffers_to_guard]
        loss = self.compute_loss(batch, step)
        loss.backward()
        value = loss.detach()
        if self.distributed:
            value = value.clone()
            dist.all_reduce(value)
            value /= dist.get_world_size()
        out = apply_gradients(self.params, self.optimizer, float(value), self.cfg.clip_grad)
        if out.skipped:
            with torch.no_grad():
                for b, s in zip(self._buffers_to_guard, saved):
                    b.copy_(s)
        return out

    @torch.no_grad()
    def validate(self, batches: list[dict[str, torch.Tensor]]) -> dict[str, float]:
        """Mean of :data:`mcdenoise.train.runlog.VAL_METRICS` over whole validation images."""
        from mcdenoise.eval.metrics import compute_metrics

        if not batches:
            return {}
        self.model.eval()
        batches = [{k: v for k, v in b.items() if k != "noisy"} for b in batches]
        sums = {m: 0.0 for m in VAL_METRICS}
        for b in batches:
            b = {k: v.to(self.device) for k, v in b.items()}
            pred = self.model(b).float()
            for k, v in compute_metrics(pred, b["target"], list(VAL_METRICS)).items():
                sums[k] += v
        self.model.train()
        return {k: v / len(batches) for k, v in sums.items()}

    @staticmethod
    def noisy_baseline(batches: list[dict[str, torch.Tensor]]) -> dict[str, float]:
        """:meth:`validate`'s metrics for the noisy input itself (the figure a model must beat)."""
        from mcdenoise.eval.metrics import compute_metrics

        sums = {m: 0.0 for m in VAL_METRICS}
        with_noisy = [b for b in batches if "noisy" in b]
        for b in with_noisy:
            for k, v in compute_metrics(b["noisy"].float(), b["target"].float(), list(VAL_METRICS)).items():
                sums[k] += v
        return {k: v / len(with_noisy) for k, v in sums.items()} if with_noisy else {}

    def state(self, step: int, skipped: int, wall_s: float = 0.0) -> dict[str, Any]:
        """Everything besides the weights that a resume needs (tensors, numbers and strings only).

        ``wall_s``: training wall time up to this checkpoint, summed over resumed calls.
        """
        st: dict[str, Any] = {"format": 1, "optimizer": self.optimizer.state_dict(), "rng_cpu": torch.get_rng_state(),
                              "skipped": skipped, "wall_s": float(wall_s)}
        if self.device.type == "cuda":
            st["rng_cuda"] = torch.cuda.get_rng_state(self.device)
        return st

    def load_state(self, st: dict[str, Any]) -> int:
        """Restore optimizer and RNG state; returns the skipped-update count so far."""
        self.optimizer.load_state_dict(st["optimizer"])
        torch.set_rng_state(st["rng_cpu"])
        if self.device.type == "cuda" and "rng_cuda" in st:
            torch.cuda.set_rng_state(st["rng_cuda"], self.device)
        return int(st.get("skipped", 0))


