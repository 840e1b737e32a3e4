"""What the paper reproductions share: the experiment description, the procedural data cache,
one training run per variant through :func:`mcdenoise.train.train`, and the result JSON.

Layout of ``--out`` (default ``runs/repro``)::

    data/                                  procedural dataset rendered on first use (all experiments)
    <experiment>/<steps>steps_seed<S>_data<H>/<variant>/   one training run folder per variant
    <experiment>/<steps>steps_seed<S>_data<H>/result.json  every figure of the comparison
    <experiment>/<steps>steps_seed<S>_data<H>/val_loss.png validation metric against steps

``H`` is the start of the dataset manifest's SHA-256, so another ``--data`` never collides with
(or is refused by) an earlier run folder. A rerun resumes unfinished runs and skips finished
ones (the training engine's ``--resume``).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from mcdenoise.errors import McDenoiseError
from mcdenoise.io.atomic import atomic_file
from mcdenoise.repro.report import METRIC_NAMES, plot_curves

__all__ = [
    "Variant",
    "Experiment",
    "CACHE_DATASET",
    "procedural_cache",
    "describe_data",
    "ReproDataError",
    "run_dir",
    "run_experiment",
    "METRIC_NAMES",
]

@dataclass(frozen=True)
class Variant:
    """One network of a comparison: a registered model's ``small`` preset plus config overrides."""

    key: str
    """Folder name and JSON key."""
    label: str
    """The paper's name for it (table rows)."""
    model: str
    """Registered model name."""
    overrides: tuple[tuple[str, Any], ...] = ()
    """Model config fields replaced (``TrainConfig.model_overrides``), as pairs so the spec is hashable."""


@dataclass(frozen=True)
class Experiment:
    """One paper claim: variants trained at an equal budget, compared on one validation metric."""

    name: str
    """CLI name (``mcdenoise repro NAME``); also the folder under ``--out``."""
    title: str
    """Heading of the Markdown block."""
    claim: str
    """The paper's claim, with the figures of its table or figure quoted (Markdown)."""
    variants: tuple[Variant, ...]
    metric: str
    """Validation metric the verdict is taken on (a key of :data:`METRIC_NAMES`)."""
    steps: int
    """Default optimizer steps per variant (sized for ~10 minutes in all on the 2-core machine)."""
    judge: Callable[[dict[str, Any]], tuple[str, str]]
    """``result -> (verdict, explanation)``; verdict is "agrees", "disagrees", "partly" or
    "inconclusive" (every difference within the runs' own spread)."""
    batch: int = 4
    crop: int = 32
    validations: int = 6
    """Validation points per run (the curve's resolution)."""
    train_overrides: tuple[tuple[str, Any], ...] = ()
    """Extra :class:`~mcdenoise.train.config.TrainConfig` fields shared by every variant."""
    paper_figures: dict[str, dict[str, float]] = field(default_factory=dict)
    """variant key -> the paper's figures for it (``{"relmse": 0.0382}``), for the table."""
    notes: str = ""
    """Experiment-specific caveats for the Markdown block."""


#: The procedural dataset rendered into ``<out>/data`` when no ``--data`` is given: 10 scenes x 4
#: views of 48x48 at 8 spp with 128-spp references, scenes split 7 train / 3 val (the val images
#: are held-out scenes). About 3-5 minutes on the 2-core machine, once.
CACHE_DATASET: dict[str, Any] = dict(count=10, seed=10, spp=8, ref_spp=128, width=48, height=48, views=4,
                                     objects=(10, 25), fractions=(0.7, 0.3, 0.0))


def procedural_cache(root: Path, log: Callable[[str], None] = print) -> Path:
    """Render (or finish rendering) :data:`CACHE_DATASET` into ``root``; returns ``root``.

    Already complete: returns without importing the renderer.
    """
    from mcdenoise.data.dataset import read_manifest

    want = CACHE_DATASET["count"] * CACHE_DATASET["views"]
    if (root / "manifest.json").is_file() and len(read_manifest(root)) == want:
        return root
    from mcdenoise.render._mitsuba import set_variant
    from mcdenoise.render.procedural_dataset import DatasetConfig, render_dataset

    set_variant("auto")
    log(f"rendering the reproductions' dataset into {root} (once; about 3-5 minutes on 2 cores)")
    t0 = time.perf_counter()
    render_dataset(root, DatasetConfig(**CACHE_DATASET), progress=False, log=log)
    log(f"dataset ready in {time.perf_counter() - t0:.0f} s")
    return root


class ReproDataError(McDenoiseError, ValueError):
    """The ``--data`` of a reproduction cannot serve it (no held-out split, no references)."""


def describe_data(data: Path) -> dict[str, Any]:
    """Image counts per split, size, spp and whether validation has references.

    Raises :class:`ReproDataError` (one line naming the folder and the fix) when a split is
    missing or an image has no reference: the variants train and are judged against references,
    so data rendered with ``--ref-spp 0`` (README's training data) cannot feed them."""
    from mcdenoise.data.dataset import Dataset

    ds = Dataset(data)
    train, val = ds.images("train"), ds.images("val")
    if not train or not val:
        raise ReproDataError(f"{data}: the reproductions need a train and a val split (held-out scenes)")
    bare = [im for im in [*train, *val] if not im.has_reference]
    if bare:
        raise ReproDataError(
            f"{data}: {len(bare)} of {len(train) + len(val)} train/val images have no reference.exr (rendered with "
            "--ref-spp 0?); the reproductions train and validate against references: render the dataset with "
            "--ref-spp 64 or more, or leave out --data so repro renders its own")
    m = val[0].meta
    return {"path": str(data), "train_images": len(train), "val_images": len(val), "val_scenes": len(ds.scenes("val")),
            "width": m.width, "height": m.height, "spp": m.spp,
            "val_references": all(im.has_reference for im in val),
            "reference_spp": m.reference_spp if val[0].has_reference else None}


def run_dir(out: Path, exp: Experiment, steps: int, seed: int, data: Path) -> Path:
    from mcdenoise.train.config import manifest_hash

    return Path(out) / exp.name / f"{steps}steps_seed{seed}_data{manifest_hash(data)[:8]}"


def _train_config(exp: Experiment, v: Variant, data: Path, steps: int, seed: int, progress: bool = False) -> Any:
    from mcdenoise.train.config import TrainConfig

    # Rounded up: `validations` evenly spaced points, the last at the final step (not one just before it).
    val_every = max(1, math.ceil(steps / exp.validations))
    # One torch thread: on the shared 2-core machine, OpenMP threads spinning against other jobs
    # made a step 5-20x slower than one thread (measured: KPCN 1.8 s vs 0.17 s at load ~7).
    return TrainConfig(model=v.model, preset="small", model_overrides=dict(v.overrides), data=str(data), steps=steps,
                       batch=exp.batch, crop=exp.crop, seed=seed, val_every=val_every, val_images=None,
                       checkpoint_every=val_every, keep_every=0, workers=0, threads=1, progress=progress,
                       **dict(exp.train_overrides))


def _parameters(v: Variant) -> int:
    from mcdenoise.models.weights import model_from_config

    return sum(p.numel() for p in model_from_config(v.model, "small", dict(v.overrides)).parameters())


def _curve(run: Path) -> list[dict[str, float]]:
    """Validation rows of a run: ``[{"step": s, "relmse": ..., "smape": ..., "l1": ..., "psnr": ...}]``."""
    from mcdenoise.train.runlog import read_metrics

    out = []
    for r in read_metrics(run / "metrics.csv"):
        if r.get("val_relmse") in (None, ""):
            continue
        out.append({"step": int(r["step"]), **{m: float(r[f"val_{m}"]) for m in METRIC_NAMES}})
    return out


def run_experiment(exp: Experiment, *, data: str | Path | None = None, steps: int | None = None, seed: int = 0,
                   out: str | Path = "runs/repro", log: Callable[[str], None] = print,
                   progress: bool = False) -> dict[str, Any]:
    """Train every variant of ``exp`` (resuming or skipping finished runs); write and return the result.

    Returns the dict written to ``result.json`` (see :func:`run_dir`); ``result["json"]`` and
    ``result["plot"]`` name the files. ``progress`` shows the engine's progress bar per run.
    """
    import torch

    threads = torch.get_num_threads()  # the runs use 1 (see _train_config); give the caller its own back
    try:
        return _run_experiment(exp, data, steps, seed, Path(out), log, progress)
    finally:
        torch.set_num_threads(threads)


def _run_experiment(exp: Experiment, data: str | Path | None, steps: int | None, seed: int, out: Path,
                    log: Callable[[str], None], progress: bool) -> dict[str, Any]:
    from mcdenoise.train.loop import train

    data_dir = Path(data) if data is not None else procedural_cache(out / "data", log)
    steps = steps or exp.steps
    info = describe_data(data_dir)
    folder = run_dir(out, exp, steps, seed, data_dir)
    variants: dict[str, Any] = {}
    t0 = time.perf_counter()
    for i, v in enumerate(exp.variants, 1):
        run = folder / v.key
        finished = (run / "result.json").is_file()
        log(f"[{exp.name}] {i}/{len(exp.variants)} {v.label}: " + ("finished earlier, skipped" if finished else f"training {steps} steps"))
        if not finished:
            train(_train_config(exp, v, data_dir, steps, seed, progress), run, resume=True)
        curve = _curve(run)
        if not curve or not all(math.isfinite(p[exp.metric]) for p in curve):
            raise RuntimeError(f"{run}: no finite validation values of {exp.metric}; see its metrics.csv")
        summary = json.loads((run / "result.json").read_text())
        variants[v.key] = {"label": v.label, "model": v.model, "overrides": dict(v.overrides),
                           "parameters": _parameters(v), "wall_s": summary["wall_s"], "device": summary["device"],
                           "run": str(run), "curve": curve, "final": {m: curve[-1][m] for m in METRIC_NAMES}}
        log(f"[{exp.name}] {v.label}: final val {METRIC_NAMES[exp.metric]} {curve[-1][exp.metric]:.5g}")
    result: dict[str, Any] = {
        "experiment": exp.name, "title": exp.title, "claim": exp.claim, "metric": exp.metric,
        "steps": steps, "default_steps": exp.steps, "batch": exp.batch, "crop": exp.crop, "seed": seed,
        "train_overrides": {k: list(v) if isinstance(v, tuple) else v for k, v in exp.train_overrides},
        "data": info, "default_data": data is None, "paper": exp.paper_figures,
        "variants": variants, "wall_s_this_call": time.perf_counter() - t0,
        "wall_s_training": sum(v["wall_s"] for v in variants.values()),
    }
    result["verdict"], result["explanation"] = exp.judge(result)
    result["plot"] = str(plot_curves(result, folder / "val_loss.png"))
    result["json"] = str(folder / "result.json")
    with atomic_file(folder / "result.json") as tmp:
        tmp.write_text(json.dumps(result, indent=1) + "\n")
    return result
