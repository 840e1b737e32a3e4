"""Training and validation batches for any registered model, from a dataset folder.

Batch ``t`` of a run is a pure function of ``(cfg.seed, t)``: row ``j`` of the global batch is
drawn with ``numpy.random.default_rng([seed, t, j + 1])`` and the batch-wide sample count with
``default_rng([seed, t])``. Hence a resumed run (``start_step``) sees exactly the batches it would
have seen, ranks of a distributed run take disjoint rows of the same global batch, and the
number of loader workers changes nothing but speed.

Reading happens in torch DataLoader worker processes (persistent, prefetching), each with its
own :class:`~mcdenoise.data.sampler.CropSampler` and its own cache of decoded EXRs.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mcdenoise.data.dataset import Dataset, dataset_dirs
from mcdenoise.data.format import ImageFolder
from mcdenoise.data.tensors import input_arrays
from mcdenoise.data.sampler import SAMPLINGS, TARGETS, Crop, CropSampler
from mcdenoise.train.augment import NUM_OPS, augment_arrays, camera_frame, draw_exposure, scale_exposure

__all__ = ["DataConfig", "training_batches", "validation_batches", "target_channels", "batch_source", "split_images"]


def split_images(spec: str | os.PathLike | list, split: str) -> list[ImageFolder]:
    """The ``split`` images of every dataset in ``spec`` (see
    :func:`mcdenoise.data.dataset.dataset_dirs`), in order: training draws from their union."""
    return [im for d in dataset_dirs(spec) for im in Dataset(d).images(split)]


@dataclass
class DataConfig:
    """How training crops are drawn. ``batch`` is the GLOBAL batch (all ranks together)."""

    crop: int = 48
    """Crop edge in pixels (square: quarter-turn augmentation needs it)."""
    batch: int = 8
    """Crops per optimiser step over all ranks; each rank gets ``batch / world_size`` rows."""
    spp_range: tuple[int, int] | None = (2, 8)
    """Input samples per pixel drawn uniformly in ``lo..hi`` (SBMC: 2..8): one count per batch for
    sample models (they take ``(B, S, ...)``), one per row for pixel models (means and variances
    recomputed from that subset). None: all stored samples / the stored noisy.exr."""
    sampling: str = "importance"
    """``"importance"`` (KPCN Sec. 5.1, toward noisy and detailed regions) or ``"uniform"``."""
    augment: bool = True
    """Random flips and quarter turns (:mod:`mcdenoise.train.augment`)."""
    exposure: tuple[float, float] | None = None
    """Each crop's radiance-like inputs and targets times one factor drawn log-uniformly in
    ``(lo, hi)`` (variances by its square); None: as rendered."""
    workers: int = 2
    """DataLoader worker processes; 0 reads in the training process."""
    target: str = "reference"
    """``"reference"`` (reference.exr) or ``"noisy"`` (Noise2Noise: mean of the held-out samples)."""
    seed: int = 0
    """Data seed; with the step index it fixes every crop."""
    accept_after: int = 8
    """Importance sampling: accept a candidate window after this many rejections."""
    prefetch: int = 4
    """Batches each worker prepares ahead."""
    max_cached: int = 16
    """Images whose decoded EXRs each worker keeps in memory (about 7 MB per 128x128 image
    with a reference; raise it for small datasets of small images, lower it for large images)."""

    def __post_init__(self) -> None:
        if self.sampling not in SAMPLINGS:
            raise ValueError(f"sampling must be one of {SAMPLINGS}, got {self.sampling!r}")
        if self.target not in TARGETS:
            raise ValueError(f"target must be one of {TARGETS}, got {self.target!r}")
        if self.crop < 1 or self.batch < 1 or self.workers < 0:
            raise ValueError(f"need crop >= 1, batch >= 1, workers >= 0; got {self}")
        if self.spp_range is not None:
            self.spp_range = (int(self.spp_range[0]), int(self.spp_range[1]))
            if not 1 <= self.spp_range[0] <= self.spp_range[1]:
                raise ValueError(f"spp_range must be (lo, hi) with 1 <= lo <= hi, got {self.spp_range}")
        if self.exposure is not None:
            self.exposure = (float(self.exposure[0]), float(self.exposure[1]))
            if not 0 < self.exposure[0] <= self.exposure[1] < float("inf"):
                raise ValueError(f"exposure must be (lo, hi) with 0 < lo <= hi, got {self.exposure}")


def target_channels(model: torch.nn.Module) -> list[str]:
    """Reference channels the model's loss compares against: ``radiance`` plus, for split
    KPCN/DPCN, ``diffuse`` and ``specular`` (their per-branch loss, see ``branch_targets``)."""
    names = ["radiance"]
    if hasattr(model, "branch_targets") and getattr(getattr(model, "config", None), "split", False):
        names += ["diffuse", "specular"]
    return names


def _input_channels(model: torch.nn.Module) -> list[str]:
    return [c for c in model.required_channels() if c != "scene_features"]


def _cap_spp(cfg: DataConfig, images: list[ImageFolder]) -> tuple[int, int] | None:
    """``cfg.spp_range`` limited to what every image with per-sample data can give (a noisy target
    keeps half); a pixel-only image is read at its own spp and limits nothing."""
    if cfg.spp_range is None:
        return None
    with_samples = [im for im in images if im.samples is not None] or images
    top = min(im.meta.spp for im in with_samples)
    if cfg.target == "noisy":
        top = max(1, top // 2)
    lo, hi = cfg.spp_range
    hi = min(hi, top)
    return (min(lo, hi), hi)


def _sampler(images: list[ImageFolder], model: torch.nn.Module, cfg: DataConfig) -> CropSampler:
    return CropSampler(
        images,
        crop=cfg.crop,
        channels=_input_channels(model),
        kind=model.input_kind,
        spp_range=_cap_spp(cfg, images),
        reference=target_channels(model),
        seed=cfg.seed,
        max_cached=cfg.max_cached,
        sampling=cfg.sampling,
        accept_after=cfg.accept_after,
        target=cfg.target,
    )


def _stack(crops: list[Crop], spp: list[int], input_kind: str, targets: list[str]) -> dict[str, torch.Tensor]:
    out: dict[str, torch.Tensor] = {}
    for name in crops[0].inputs:
        out[name] = torch.from_numpy(np.stack([c.inputs[name] for c in crops]))
    if input_kind == "samples":
        out["scene_features"] = torch.from_numpy(np.stack([c.scene_features for c in crops]))
    out["target"] = torch.from_numpy(np.stack([c.reference["radiance"] for c in crops]))
    for name in targets[1:]:
        out[f"target:{name}"] = torch.from_numpy(np.stack([c.reference[name] for c in crops]))
    out["spp"] = torch.tensor(spp, dtype=torch.int64)
    return out


class _BatchSource(torch.utils.data.Dataset):
    """Map-style dataset: index ``t`` -> this rank's rows of global batch ``t`` (a dict of tensors)."""

    def __init__(self, sampler: CropSampler, cfg: DataConfig, rows: range) -> None:
        self.sampler, self.cfg, self.rows = sampler, cfg, rows
        self.targets = list(sampler.reference)
        self.metas = {im.path: im.meta for im in sampler.images}
        self._frames: dict[Path, np.ndarray | None] = {p: camera_frame(m.extra) for p, m in self.metas.items()}

    def __len__(self) -> int:  # nominal; the step sampler decides what is read
        return 2**62

    def __getitem__(self, t: int) -> dict[str, torch.Tensor]:
        s = self.sampler
        seed = self.cfg.seed
        n_batch: int | None = None
        if s.kind == "samples" and s.spp_range is not None:
            lo, hi = s.spp_range
            n_batch = int(np.random.default_rng([seed, int(t)]).integers(lo, hi + 1))
        crops: list[Crop] = []
        spp: list[int] = []
        for j in self.rows:
            rng = np.random.default_rng([seed, int(t), j + 1])
            c = s.draw(rng, spp=n_batch)
            if self.cfg.augment:
                op = int(rng.integers(NUM_OPS))
                frame = self._frames[c.path]
                c.inputs = augment_arrays(c.inputs, op, frame)
                c.reference = augment_arrays(c.reference, op, frame)
            if self.cfg.exposure is not None:  # drawn last: runs without it keep their crops
                k = draw_exposure(rng, self.cfg.exposure)
                c.inputs, c.reference = scale_exposure(c.inputs, k), scale_exposure(c.reference, k)
            crops.append(c)
            spp.append(len(c.samples) if c.samples is not None else self.metas[c.path].spp)
        return _stack(crops, spp, s.kind, self.targets)


class _Steps:
    """The step indices ``start, start + 1, ...`` (endless) as a DataLoader sampler."""

    def __init__(self, start: int) -> None:
        self.start = start

    def __iter__(self) -> Iterator[int]:
        return itertools.count(self.start)


def _worker_init(_: int) -> None:
    # One reader per core: numpy/torch threads inside each worker would only fight each other.
    torch.set_num_threads(1)


def batch_source(data_dir: str | os.PathLike | list, model: torch.nn.Module, cfg: DataConfig, *, rank: int = 0,
                 world_size: int = 1, split: str = "train") -> _BatchSource:
    """The map-style source behind :func:`training_batches`: ``source[t]`` is rank ``rank``'s part
    of global batch ``t`` (useful for tests and benchmarks without worker processes)."""
    if world_size < 1 or not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} outside 0..{world_size - 1}")
    if cfg.batch % world_size:
        raise ValueError(f"global batch {cfg.batch} is not divisible by world_size {world_size}")
    images = split_images(data_dir, split)
    if not images:
        raise ValueError(f"{data_dir}: no images in the {split!r} split")
    per = cfg.batch // world_size
    return _BatchSource(_sampler(images, model, cfg), cfg, range(rank * per, (rank + 1) * per))


def training_batches(
    data_dir: str | os.PathLike,
    model: torch.nn.Module,
    cfg: DataConfig,
    *,
    start_step: int = 0,
    rank: int = 0,
    world_size: int = 1,
    device: torch.device | str = "cpu",
) -> Iterator[dict[str, torch.Tensor]]:
    """Endless training batches from ``data_dir``'s train split, batch ``start_step`` first.

    Each batch holds, for this rank's ``B = cfg.batch / world_size`` rows:

    * the model's inputs: ``required_channels()`` as ``(B, C, h, w)`` (pixel models) or
      ``(B, S, C, h, w)`` plus ``scene_features (B, F)`` (sample models; one ``S`` per batch);
    * ``target (B, 3, h, w)``: reference radiance (or the held-out-sample mean, ``target="noisy"``),
      and ``target:<name>`` for each other channel of :func:`target_channels`;
    * ``spp (B,)`` int64: input samples per pixel of each row (for logging).
    """
    source = batch_source(data_dir, model, cfg, rank=rank, world_size=world_size)
    from mcdenoise.data.oidn_input import split_oidn

    derived = split_oidn(_input_channels(model))[1]
    if derived:
        precompute_oidn(split_images(data_dir, "train"), cfg, derived)
    dev = torch.device(device)
    loader = torch.utils.data.DataLoader(
        source,
        batch_size=None,
        sampler=_Steps(start_step),
        num_workers=cfg.workers,
        persistent_workers=cfg.workers > 0,
        prefetch_factor=cfg.prefetch if cfg.workers > 0 else None,
        worker_init_fn=_worker_init if cfg.workers > 0 else None,
        pin_memory=dev.type == "cuda",
    )
    for batch in loader:
        yield {k: v.to(dev, non_blocking=True) for k, v in batch.items()}


def precompute_oidn(images: list, cfg: DataConfig, channels: list[str] | None = None) -> None:
    """Fill the OIDN cache for every input sample count a crop can draw, here, before the loader
    forks its workers: OIDN's TBB thread pool does not survive a fork (a worker computing OIDN
    after the parent ran it hangs), and each (image, spp) is paid for once (issue 20).
    ``channels``: the derived OIDN channels to fill (default ``["oidn"]``)."""
    import sys

    from mcdenoise.data.oidn_input import oidn_for

    todo = []
    for im in images:
        m = im.meta
        if im.samples is None:  # pixel-only: its own spp, nothing else
            counts = [None]
        elif cfg.spp_range is not None:
            counts = range(cfg.spp_range[0], min(cfg.spp_range[1], m.spp - (cfg.target == "noisy")) + 1)
        else:
            counts = [m.spp // 2] if cfg.target == "noisy" else [None]
        todo += [(im, k) for k in counts]
    channels = channels or ["oidn"]
    print(f"OIDN inputs: {len(todo)} (image, spp) pairs x {', '.join(channels)}, cached beside the dataset", file=sys.stderr)
    for im, k in todo:
        for ch in channels:
            oidn_for(im, k, channel=ch)


def validation_batches(
    data_dir: str | os.PathLike,
    model: torch.nn.Module,
    cfg: DataConfig,
    *,
    max_images: int | None = None,
) -> list[dict[str, torch.Tensor]]:
    """Whole images of the ``val`` split as batches of one, deterministic (no crop, no augmentation).

    Inputs use the first ``hi`` stored samples (``hi`` = the top of ``spp_range``, capped at the
    stored spp; all samples / noisy.exr without ``spp_range``). The target is reference.exr when
    the image has one, else the mean of the samples the input did not use. Returns ``[]`` when
    the dataset has no ``val`` images.
    """
    images = split_images(data_dir, "val")[: max_images if max_images is not None else None]
    names = _input_channels(model)
    targets = target_channels(model)
    out = []
    for im in images:
        m = im.meta
        hi = m.spp
        if cfg.spp_range is not None:
            hi = min(cfg.spp_range[1], m.spp if im.has_reference else max(1, m.spp // 2))
        elif not im.has_reference:
            hi = max(1, m.spp // 2)
        idx = list(range(hi))
        inputs = input_arrays(im, names, model.input_kind, spp=hi)
        if im.has_reference:
            ref = im.read_reference(targets)
        else:
            held = list(range(hi, m.spp))
            if not held:
                raise ValueError(f"{im.path}: no reference and no held-out samples for a validation target")
            ref = {k: v.mean(axis=0) for k, v in im.samples.read(targets, samples=held).items()}
        crop = Crop(inputs, ref, m.scene_feature_vector(), im.path, (0, 0), idx)
        batch = _stack([crop], [hi], model.input_kind, targets)
        # The noisy input's own image, so that validation can print the baseline beside the model.
        noisy = (im.read_noisy(["radiance"])["radiance"] if im.samples is None  # a pixel-only image (no samples.bin)
                 else im.samples.read(["radiance"], samples=idx)["radiance"].mean(axis=0))
        batch["noisy"] = torch.from_numpy(noisy)[None].float()
        out.append(batch)
    return out
