"""Training configuration: one dataclass with a docstring per field, per-model paper defaults,
and the ``config.json`` that a run folder keeps and ``--resume`` compares against.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcdenoise.errors import McDenoiseError
from mcdenoise.train.losses import LOSSES, get_loss

__all__ = [
    "TrainConfig",
    "ModelDefaults",
    "MODEL_DEFAULTS",
    "model_defaults",
    "RUNTIME_FIELDS",
    "ConfigError",
    "manifest_hash",
    "config_document",
    "check_resume_config",
]


class ConfigError(McDenoiseError):
    """A training setting is invalid or does not match the run folder (printed as one line)."""


@dataclass(frozen=True)
class ModelDefaults:
    """What a model trains with when the command does not say otherwise.

    Attributes:
        loss: registered loss name (the paper's).
        lr: Adam learning rate used here (small presets, ~1 CPU-hour budgets).
        paper_lr: the paper's learning rate, for the docs.
        branch_fraction: fraction of the steps spent on per-branch losses before the loss moves
            to the recombined image (KPCN Sec. 4.3); 0 = image loss throughout.
    """

    loss: str
    lr: float
    paper_lr: float
    branch_fraction: float = 0.0


#: Per-family defaults. KPCN's 1e-5 needs ~1M steps; in a 100-step trial on a 5-image 64x64
#: dataset (docs/TRAINING.md) 3e-4 reached validation relMSE 0.14 where 1e-5 reached 0.41; SBMC's
#: 1e-4 likewise trailed 3e-4. The layer paper's 5e-3 beat 1e-3 in the same trial (SMAPE 0.156 vs
#: 0.175), so it stays. WSKP's 1e-3 is the paper's, untested here.
MODEL_DEFAULTS: dict[str, ModelDefaults] = {
    "kpcn": ModelDefaults("l1", 3e-4, 1e-5, branch_fraction=0.8),
    "dpcn": ModelDefaults("l1", 3e-4, 1e-5, branch_fraction=0.8),
    "kpcn_single": ModelDefaults("l1", 3e-4, 1e-5, branch_fraction=0.8),
    "sbmc": ModelDefaults("tonemapped_l2", 3e-4, 1e-4),
    "sbmc_gather": ModelDefaults("tonemapped_l2", 3e-4, 1e-4),
    "pixel_gather": ModelDefaults("tonemapped_l2", 3e-4, 1e-4),
    "pixel_splat": ModelDefaults("tonemapped_l2", 3e-4, 1e-4),
    "layer": ModelDefaults("smape", 5e-3, 5e-3),
    "layer_optimized": ModelDefaults("smape", 5e-3, 5e-3),
    "layer_weighted": ModelDefaults("smape", 5e-3, 5e-3),
    "wskp": ModelDefaults("smape", 1e-3, 1e-3),
    "wskp_mr": ModelDefaults("smape", 1e-3, 1e-3),
    # Not a paper's model: relMSE (unbiased against noisy targets, exposure-invariant).
    "combine": ModelDefaults("relmse", 1e-3, 1e-3),
}

#: A model registered later without an entry above trains with these.
_FALLBACK = ModelDefaults("smape", 1e-3, 1e-3)


def model_defaults(name: str) -> ModelDefaults:
    return MODEL_DEFAULTS.get(name, _FALLBACK)


@dataclass
class TrainConfig:
    """Every setting of one training run. ``None`` fields are resolved by :meth:`resolved`."""

    model: str = "kpcn"
    """Registered model name (``mcdenoise models`` lists them)."""
    preset: str = "small"
    """Model preset (``small`` for CPU budgets, ``paper`` for the published sizes)."""
    model_overrides: dict[str, Any] = field(default_factory=dict)
    """Fields of the preset's model configuration replaced for this run, e.g. ``{"layers": 4}``
    (ablations such as ``mcdenoise repro``); the run's ``model_config`` records the result."""
    init: str | None = None
    """Start from these weights (fine-tuning): a shipped model name, a run folder or a
    ``.safetensors`` file of the same model; its model configuration replaces the preset's."""
    data: str = ""
    """Dataset folder written by ``mcdenoise dataset`` (needs a ``train`` split; ``val`` for validation);
    several separated by commas train on the union of their images."""
    val_data: str | None = None
    """Validate on this dataset's ``val`` split instead (e.g. a small one with references: noisy
    targets make validation relMSE biased); None = ``data``'s."""
    steps: int = 2000
    """Number of optimizer steps (one global batch each)."""
    batch: int = 8
    """Global batch: crops per step over all processes together (must divide by the process count)."""
    crop: int = 48
    """Crop edge in pixels."""
    lr: float | None = None
    """Peak Adam learning rate; None = the model's default (see MODEL_DEFAULTS)."""
    loss: str | None = None
    """Registered loss (l1, l2, relmse, smape, tonemapped_l2, log_l1); None = the paper's."""
    target: str = "reference"
    """``reference`` (converged render) or ``noisy`` (an independent noisy render, Noise2Noise)."""
    sampling: str = "importance"
    """Crop placement: ``importance`` (toward noisy, detailed regions, KPCN Sec. 5.1) or ``uniform``."""
    spp_range: tuple[int, int] | None = None
    """Random input spp drawn in this range; None = (2, 8) for sample models (SBMC), the stored
    noisy image for pixel models. The data side clips it to what the dataset holds."""
    augment: bool = True
    """Random flips and 90-degree rotations (normals and motion transformed with the image)."""
    exposure: tuple[float, float] | None = None
    """Exposure augmentation: each crop (inputs and target) times a factor log-uniform in
    ``(lo, hi)``; None = as rendered."""
    seed: int = 0
    """Seeds the weights and every batch: batch t is a pure function of (seed, t)."""
    warmup: float = 0.02
    """Fraction of the steps with a linear learning-rate warm-up from 0."""
    schedule: str = "cosine"
    """Decay after warm-up: ``cosine`` (to min_lr_fraction), ``step`` (x0.1 at 50% and 75%), ``constant``."""
    min_lr_fraction: float = 0.05
    """Final learning rate of the cosine schedule, as a fraction of the peak."""
    clip_grad: float = 1.0
    """Clip the global gradient norm to this (0 = no clipping)."""
    branch_fraction: float | None = None
    """Fraction of steps on per-branch losses (KPCN/DPCN); None = the model's default; 0 under noisy targets."""
    amp: str = "none"
    """``bf16``: autocast the forward pass to bfloat16 (CUDA, or a CPU with native bfloat16:
    AVX512-BF16/AMX; emulated elsewhere, so slower); losses, weights and optimiser stay float32;
    ``none``: float32."""
    device: str = "auto"
    """``cpu``, ``cuda`` or ``auto`` (CUDA when available)."""
    workers: int = 2
    """Data-loader worker processes per training process (0 = read in the training process)."""
    threads: int = 0
    """Torch intra-op threads of each training process (0 = torch's default). On a small machine
    shared with loader workers, 1 avoids OpenMP threads spinning against each other."""
    val_every: int = 200
    """Validate on the ``val`` split every this many steps and at the end (0 = only at the end)."""
    val_images: int | None = 8
    """At most this many validation images (None = all)."""
    checkpoint_every: int = 100
    """Write ``checkpoints/latest`` every this many steps and at the end."""
    keep_every: int = 1000
    """Also keep the checkpoint of every multiple of this many steps (0 = only the latest)."""
    progress: bool = True
    """Show a progress bar (rank 0 only)."""

    def resolved(self, model_input_kind: str) -> TrainConfig:
        """A copy with every ``None`` replaced by its concrete default, checked.

        Args:
            model_input_kind: ``"samples"`` or ``"pixels"`` (the model's ``input_kind``).
        """
        d = model_defaults(self.model)
        c = dataclasses.replace(self)
        c.loss = c.loss or d.loss
        c.lr = c.lr if c.lr is not None else d.lr
        if c.branch_fraction is None:
            c.branch_fraction = 0.0 if c.target == "noisy" else d.branch_fraction
        if c.spp_range is None and model_input_kind == "samples":
            c.spp_range = (2, 8)
        c.check()
        return c

    def check(self) -> None:
        """Raise :class:`ConfigError` (one line) on an invalid combination."""
        loss = None
        if self.loss is not None:
            try:
                loss = get_loss(self.loss)
            except KeyError as e:
                raise ConfigError(str(e.args[0])) from None
        if self.target not in ("reference", "noisy"):
            raise ConfigError(f"target must be 'reference' or 'noisy', got {self.target!r}")
        if self.target == "noisy" and loss is not None and not loss.unbiased_for_noisy_target:
            ok = ", ".join(sorted(n for n, l in LOSSES.items() if l.unbiased_for_noisy_target))
            raise ConfigError(f"loss {self.loss!r} is biased for noisy targets; use one of: {ok}")
        if self.target == "noisy" and self.branch_fraction:
            raise ConfigError("per-branch pre-training works in the log domain, which is biased for noisy targets; set branch_fraction 0")
        if self.sampling not in ("importance", "uniform"):
            raise ConfigError(f"sampling must be 'importance' or 'uniform', got {self.sampling!r}")
        if self.schedule not in ("cosine", "step", "constant"):
            raise ConfigError(f"schedule must be cosine, step or constant, got {self.schedule!r}")
        if self.amp not in ("none", "bf16"):
            raise ConfigError(f"amp must be 'none' or 'bf16', got {self.amp!r}")
        if self.steps < 1 or self.batch < 1 or self.crop < 1:
            raise ConfigError(f"steps, batch and crop must be >= 1 (got {self.steps}, {self.batch}, {self.crop})")
        if self.lr is not None and not self.lr > 0:
            raise ConfigError(f"lr must be > 0, got {self.lr}")
        if not 0 <= self.warmup < 1 or not 0 <= (self.branch_fraction or 0) <= 1:
            raise ConfigError("warmup must be in [0, 1) and branch_fraction in [0, 1]")
        if self.spp_range is not None and not 1 <= self.spp_range[0] <= self.spp_range[1]:
            raise ConfigError(f"spp range {self.spp_range}: need 1 <= lo <= hi")
        if self.exposure is not None and not 0 < self.exposure[0] <= self.exposure[1] < float("inf"):
            raise ConfigError(f"exposure range {self.exposure}: need 0 < lo <= hi")
        if self.checkpoint_every < 1:
            raise ConfigError("checkpoint_every must be >= 1")

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["spp_range"] = list(self.spp_range) if self.spp_range is not None else None
        d["exposure"] = list(self.exposure) if self.exposure is not None else None
        # Tuples as lists, as they read back from config.json (a resume compares the two).
        d["model_overrides"] = json.loads(json.dumps(self.model_overrides))
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> TrainConfig:
        known = {f.name for f in dataclasses.fields(cls)}
        c = cls(**{k: v for k, v in d.items() if k in known})
        if c.spp_range is not None:
            c.spp_range = (int(c.spp_range[0]), int(c.spp_range[1]))
        if c.exposure is not None:
            c.exposure = (float(c.exposure[0]), float(c.exposure[1]))
        return c


#: Settings that do not change what is computed: a resume may change them freely.
RUNTIME_FIELDS = frozenset({"data", "val_data", "device", "workers", "threads", "val_every", "val_images", "checkpoint_every", "keep_every", "progress"})


def manifest_hash(data_dir: str | Path) -> str:
    """SHA-256 of the dataset's ``manifest.json`` bytes: names the exact image list trained on and,
    for procedural datasets that record their Mitsuba variant, the render settings (spp, size,
    seed, depth, world, generator version, variant: the manifest's ``settings`` block). Manifests
    of older datasets have no such block and keep their bytes, so runs resume against them.
    ``data_dir`` may name several datasets separated by commas (``--data a,b``)."""
    from mcdenoise.data.dataset import dataset_dirs

    hashes = [hashlib.sha256((d / "manifest.json").read_bytes()).hexdigest() for d in dataset_dirs(data_dir)]
    # One dataset keeps its plain hash (older runs resume); several hash their hashes, in order.
    return hashes[0] if len(hashes) == 1 else hashlib.sha256("\n".join(hashes).encode()).hexdigest()


def config_document(cfg: TrainConfig, *, model_config: dict[str, Any], manifest_sha256: str, world_size: int) -> dict[str, Any]:
    """What ``config.json`` holds: the resolved settings plus provenance."""
    import torch

    from mcdenoise import __version__

    return {
        "format": "mcdenoise-train-run",
        "version": 1,
        "train": cfg.to_json(),
        "model_config": model_config,
        "manifest_sha256": manifest_sha256,
        "mcdenoise_version": __version__,
        "torch_version": torch.__version__,
        "world_size": world_size,
    }


def check_resume_config(saved: dict[str, Any], current: dict[str, Any], where: Path) -> None:
    """Refuse (one line) a resume whose settings or dataset differ from the saved run's."""
    # A run saved before model_overrides existed trained without overrides.
    a, b = {"model_overrides": {}, "init": None, **saved.get("train", {})}, current["train"]
    diffs = [k for k in sorted(set(a) | set(b)) if k not in RUNTIME_FIELDS and a.get(k) != b.get(k)]
    # More steps extend a run (the schedule is then laid over the new total); fewer are refused.
    if "steps" in diffs and int(b.get("steps") or 0) > int(a.get("steps") or 0):
        diffs.remove("steps")
    if diffs:
        shown = "; ".join(f"{k}: run has {a.get(k)!r}, command gives {b.get(k)!r}" for k in diffs[:3])
        raise ConfigError(f"{where}: config does not match the command ({shown}); use another --out or --force to start over")
    if saved.get("manifest_sha256") != current["manifest_sha256"]:
        raise ConfigError(f"{where}: the dataset's manifest.json differs from the one this run trained on")
    if _with_added_defaults(saved.get("model_config"), current, b.get("model")) != current["model_config"]:
        raise ConfigError(f"{where}: the model's configuration differs from the saved run's")


def _with_added_defaults(saved_cfg: dict[str, Any] | None, current: dict[str, Any], model: str | None) -> dict[str, Any] | None:
    """``saved_cfg`` with the fields that the model's configuration class gained after the run was
    saved filled in with their defaults: the run trained as those defaults behave (e.g.
    ``autoexposure`` None), so a resume must not be refused for them."""
    from mcdenoise.models.base import MODELS

    entry = MODELS.get(model or "")
    if saved_cfg is None or entry is None:
        return saved_cfg
    out = dict(saved_cfg)
    for f in dataclasses.fields(entry.config_cls):
        if f.name in out or f.name not in current.get("model_config", {}):
            continue
        if f.default is not dataclasses.MISSING:
            out[f.name] = json.loads(json.dumps(f.default))  # tuples as lists, as config.json holds them
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            out[f.name] = json.loads(json.dumps(f.default_factory()))  # type: ignore[misc]
    return out


def read_config(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path}: cannot read ({e})") from None
    if doc.get("format") != "mcdenoise-train-run":
        raise ConfigError(f"{path}: not a training run's config.json")
    return doc
