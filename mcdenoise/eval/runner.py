"""``mcdenoise eval``: every denoiser on the same images at several sample counts, into one report.

For each image with a reference and each ``k`` of ``spp`` (the first ``k`` stored samples; a
``k`` above the stored count is skipped with a note), the noisy input, OIDN 2.5.1 (``high`` and
``fast`` by default, HDR, albedo + normal guides), feature-guided NL-means and each model run on
the same inputs; every metric of :mod:`mcdenoise.eval.metrics` is computed per image, then
averaged per (method, spp). Times: wall time of the denoise call only (inputs already read and on
the device), after one untimed warm-up call per method, under ``torch.inference_mode``; the
mean time per megapixel of a (method, spp) is total seconds over total megapixels.

The report folder (written whole, then renamed into place) holds ``results.json``,
``results.csv``, ``index.html`` with its PNGs (:mod:`mcdenoise.eval.html`); ``results_md``
also fills block ``eval:SECTION`` of a Markdown file (:mod:`mcdenoise.eval.resultsmd`).

This module runs the loop and writes the report; which images (:mod:`mcdenoise.eval.images`),
which methods (:mod:`mcdenoise.eval.lineup`) and how they are scored and averaged
(:mod:`mcdenoise.eval.scores`) live beside it.
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mcdenoise.errors import EvalError
from mcdenoise.eval.images import EvalImage, collect_images, image_effects
from mcdenoise.eval.lineup import build_methods
from mcdenoise.eval.methods import Inputs, Method
from mcdenoise.eval.metrics import METRICS
from mcdenoise.eval.provenance import provenance
from mcdenoise.eval.scores import CSV_FIELDS, SUBSETS, image_metrics, summarize, write_csv
from mcdenoise.eval.seeds import seed_spread
from mcdenoise.io.atomic import atomic_dir, atomic_file

__all__ = ["EvalError", "EvalImage", "evaluate", "collect_images", "image_effects", "build_methods", "summarize",
           "write_csv", "RESULTS_FORMAT", "CSV_FIELDS", "SUBSETS"]

RESULTS_FORMAT = "mcdenoise-eval"
RESULTS_VERSION = 1


def _check_spp(spp: Sequence[int]) -> list[int]:
    ks = sorted({int(k) for k in spp})
    if not ks:
        raise EvalError("no sample counts given (--spp needs at least one, e.g. --spp 4 8 16)")
    if ks[0] < 1:
        raise EvalError(f"sample counts must be at least 1, got {ks[0]}")
    return ks


def _device(device: str | None) -> torch.device:
    if device in (None, "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device not in ("cpu", "cuda"):
        raise EvalError(f"device must be cpu, cuda or auto, got {device!r}")
    if device == "cuda" and not torch.cuda.is_available():
        raise EvalError("--device cuda: no CUDA device is available")
    return torch.device(device)


def _run_timed(method: Method, prepared: Any, device: torch.device) -> tuple[np.ndarray, float | None]:
    if not method.timed:
        return method.run(prepared), None
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    t0 = time.perf_counter()
    out = method.run(prepared)
    return out, time.perf_counter() - t0


def _check_runnable(images: list[EvalImage], ks: list[int]) -> None:
    """Refuse sample counts no image can give (an empty report with exit 0 otherwise)."""
    def runs(im: EvalImage, k: int) -> bool:
        stored = im.folder.meta.spp
        return k == stored or (k < stored and im.folder.samples is not None)

    if images and not any(runs(im, k) for im in images for k in ks):
        stored = ", ".join(str(s) for s in sorted({im.folder.meta.spp for im in images}))
        raise EvalError(f"--spp {' '.join(map(str, ks))}: no image can be evaluated at that sample count; "
                        f"the data stores {stored} spp (choose --spp at most that)")


def evaluate(
    *,
    models: Sequence[str | os.PathLike] = (),
    data: Sequence[str | os.PathLike] | str | os.PathLike,
    out: str | os.PathLike,
    split: str = "test",
    spp: Sequence[int] = (4, 8, 16),
    oidn: Sequence[str] = ("high", "fast"),
    classic: bool = True,
    max_images: int | None = None,
    device: str | None = "auto",
    threads: int | None = None,
    precision: Sequence[str] = ("float32",),
    metrics: Sequence[str] | None = None,
    results_md: str | os.PathLike | None = None,
    section: str | None = None,
    html: bool = True,
    progress: bool = True,
    command: str | None = None,
    save_images: bool = False,
    self_ensemble: bool = False,
) -> dict[str, Any]:
    """Run the evaluation and write the report folder ``out``; returns what results.json holds.

    Args:
        models: model specs for :func:`mcdenoise.models.weights.load_denoiser` (registered name
            with shipped weights, run folder, or .safetensors file).
        data: dataset folders (images of ``split``), image folders, or folders of image folders.
        out: report folder; replaced whole when it holds an earlier report, refused when it holds
            anything else.
        spp: input sample counts k (the first k stored samples).
        oidn: OIDN qualities to run (empty: no OIDN).
        classic: run feature-guided NL-means.
        max_images: at most this many images per data folder.
        device: ``cpu``, ``cuda`` or ``auto`` (CUDA when available) for the models and NL-means.
        threads: torch CPU threads during the evaluation (default: torch's), and OIDN's too (default:
            every core), so both are timed on the same cores; 1 is much faster on a machine whose
            cores are busy with other work. Both counts are in results.json (``config.threads``,
            ``config.oidn_threads``) and under every table.
        precision: run every model in each of these (``float32``, ``bfloat16``, ``auto``; see
            :func:`mcdenoise.models.inference.prepare_inference`); bfloat16 rows are labelled
            ``+bf16``, so one report compares both.
        metrics: metric names (default: every metric of :data:`mcdenoise.eval.metrics.METRICS`).
        results_md, section: also write the tables into block ``eval:SECTION`` of this Markdown file.
        html: write index.html and its images.
        save_images: also write every full-size output as ``images/<image>/<k>spp/<method>.exr``
            (plus ``reference.exr``), as the demo does.
        progress: a tqdm bar over (image, spp) on stderr.
        command: the command line recorded in the report (default: a Python call).
        self_ensemble: also run every model as a self-ensemble of its 8 orientations
            (:mod:`mcdenoise.models.symmetry`), labelled ``+se``, beside its single pass.
    """
    ks = _check_spp(spp)
    if (results_md is None) != (section is None):
        raise EvalError("--results-md and --section go together")
    if section is not None and not re.fullmatch(r"[A-Za-z0-9_.-]+", section):
        raise EvalError(f"--section {section!r}: use only letters, digits and _.- (it names block eval:SECTION)")
    metric_names = list(metrics) if metrics is not None else list(METRICS)
    unknown = [m for m in metric_names if m not in METRICS]
    if unknown:
        raise EvalError(f"unknown metric(s) {unknown}; known: {', '.join(METRICS)}")
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "results.json").is_file())):
        raise EvalError(f"{out}: exists and is not an earlier report (no results.json); choose another --out")
    data_list = [data] if isinstance(data, (str, os.PathLike)) else list(data)
    if not data_list:
        raise EvalError("no data folder given (--data)")
    images, notes = collect_images(data_list, split, max_images)
    _check_runnable(images, ks)
    dev = _device(device)
    if threads is not None and threads < 1:
        raise EvalError(f"--threads must be at least 1, got {threads}")
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        doc = _evaluate(models, data_list, out, split, ks, list(oidn), classic, max_images, dev, metric_names,
                        images, notes, html, progress, command, save_images, tuple(precision), threads,
                        self_ensemble)
    finally:
        torch.set_num_threads(old_threads)
    if results_md is not None and section is not None:
        from mcdenoise.eval.resultsmd import write_results_md

        write_results_md(results_md, section, doc)
    return doc


def _save_images(folder: Path, k: int, outputs: dict[str, np.ndarray], ref: np.ndarray) -> None:
    """Full-size outputs as EXRs (``radiance`` layer): ``folder/<k>spp/<method>.exr`` and ``folder/reference.exr``."""
    from mcdenoise.io.exr import write_exr

    (folder / f"{k}spp").mkdir(parents=True, exist_ok=True)
    if not (folder / "reference.exr").exists():
        write_exr(folder / "reference.exr", {"radiance": ref})
    for name, y in outputs.items():
        write_exr(folder / f"{k}spp" / f"{name}.exr", {"radiance": y})


def _evaluate(models: Sequence[str | os.PathLike], data_list: list[Any], out: Path, split: str, ks: list[int],
              oidn: list[str], classic: bool, max_images: int | None, dev: torch.device, metric_names: list[str],
              images: list[EvalImage], notes: list[str], html: bool, progress: bool, command: str | None,
              save_images: bool = False, precisions: tuple[str, ...] = ("float32",),
              threads: int | None = None, self_ensemble: bool = False) -> dict[str, Any]:
    """The evaluation loop and the report folder (arguments checked by :func:`evaluate`)."""
    from tqdm import tqdm

    methods = build_methods(models, list(oidn), classic, dev, precisions, oidn_threads=threads, notes=notes,
                            self_ensemble=self_ensemble)
    prov = provenance(dev, bool(oidn))
    if command is None:
        command = f"mcdenoise.eval.evaluate(models={list(map(str, models))}, data={list(map(str, data_list))}, " \
                  f"split={split!r}, spp={ks})"

    from mcdenoise.eval import html as report

    from mcdenoise.bench.timing import busy_warning

    busy = busy_warning("at start")
    if busy:
        notes.append(f"timing: {busy}")
    rows: list[dict[str, Any]] = []
    warmed: set[str] = set()
    pairs = [(im, k) for im in images for k in ks]
    with atomic_dir(out, overwrite=True) as tmp:
        crops = report.CropWriter(tmp) if html else None
        bar = tqdm(pairs, desc="eval", unit="img", disable=not progress, dynamic_ncols=True)
        for im, k in bar:
            bar.set_postfix_str(f"{im.id} {k} spp")
            if k > im.folder.meta.spp:
                notes.append(f"{im.id}: {k} spp skipped (stores {im.folder.meta.spp})")
                continue
            if k < im.folder.meta.spp and im.folder.samples is None:
                notes.append(f"{im.id}: {k} spp skipped (no per-sample file; only all {im.folder.meta.spp} spp)")
                continue
            ref = im.folder.read_reference(["radiance"])["radiance"]  # type: ignore[index]
            x = Inputs(im.folder, k)
            mp = im.folder.meta.width * im.folder.meta.height / 1e6
            outputs: dict[str, np.ndarray] = {}
            for m in methods:
                prepared = m.prepare(x)
                if m.timed and m.name not in warmed:
                    m.run(prepared)  # warm-up: first-call allocations, kernel compilation, OIDN's filter setup
                    warmed.add(m.name)
                y, secs = _run_timed(m, prepared, dev)
                y = np.asarray(y, dtype=np.float32)
                if y.shape != ref.shape:
                    raise EvalError(f"{m.name} returned shape {y.shape} for {im.id}, expected {ref.shape}")
                rows.append({"image": im.id, "spp": k, "method": m.name, "seconds": secs,
                             "ms_per_mpix": None if secs is None else 1e3 * secs / mp, **image_metrics(y, ref, metric_names)})
                outputs[m.name] = y
            if crops is not None:
                crops.add(im.id, k, outputs, ref)
            if save_images:
                _save_images(tmp / "images" / im.id, k, outputs, ref)
        bar.close()
        busy = busy_warning("at end")
        if busy:
            notes.append(f"timing: {busy}")
        names = [m.name for m in methods]
        doc: dict[str, Any] = {
            "format": RESULTS_FORMAT,
            "version": RESULTS_VERSION,
            "command": command,
            "provenance": prov,
            "config": {"models": [str(s) for s in models], "data": [str(d) for d in data_list], "split": split,
                       "spp": ks, "oidn": list(oidn), "classic": classic, "max_images": max_images,
                       "device": str(dev), "threads": torch.get_num_threads(),
                       "oidn_threads": next((m.info["threads"] for m in methods if m.kind == "oidn"), None),
                       "metrics": metric_names},
            "methods": [m.info for m in methods],
            "images": [im.to_json() for im in images],
            "notes": notes,
            "rows": rows,
            "summary": summarize(rows, images, names, ks, metric_names),
        }
        doc["seed_spread"] = seed_spread(rows, doc["images"])
        with atomic_file(tmp / "results.json") as f:
            f.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
        write_csv(tmp / "results.csv", rows, metric_names)
        if crops is not None:
            report.write_report(tmp, doc, crops)
    return doc
