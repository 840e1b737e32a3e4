"""Denoise an :class:`~mcdenoise.infer.sources.Inputs` with a model, in tiles sized to a memory budget."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import math

import numpy as np
import torch

from mcdenoise.data.oidn_input import OIDN_CHANNELS, oidn_guides
from mcdenoise.data.symmetry import source_box, turned_shape
from mcdenoise.errors import McDenoiseError
from mcdenoise.infer.memory import DEFAULT_MAX_MEMORY, MemoryCost, measure_cost
from mcdenoise.infer.receptive import alignment, receptive_field
from mcdenoise.infer.sources import Inputs
from mcdenoise.infer.tiling import TilePlan, plan_tiles, run_tiled
from mcdenoise.models.consistency import acts_at
from mcdenoise.models.exposure import EXPOSURE_SCALE
from mcdenoise.models.registry import Denoiser
from mcdenoise.models.symmetry import ALL_OPS, median_of, transform_batch, untransform

__all__ = ["default_device", "memory_cost", "tile_plan", "emitter_reach", "denoise_inputs", "RunInfo",
           "BUDGET_FRACTION", "describe_plan", "MIN_CORE", "BudgetError"]

#: Share of ``max_memory`` given to one tile's model call; the rest holds the whole-image output,
#: the reader's staging buffers (a window is read in its storage dtype, then converted) and Python.
BUDGET_FRACTION = 0.75

#: Images up to this many pixels run as one tile without measuring the model's memory cost (the
#: measurement's own probe is as large).
SMALL_IMAGE = 64 * 64

#: Smallest tile core (pixels a side, rounded up to the model's alignment) a memory budget may
#: ask for: smaller cores spend nearly all their time on the overlap (a 1 K budget planned 16,384
#: one-pixel tiles and ran 65x slower), so such a budget is refused instead.
MIN_CORE = 32


class BudgetError(McDenoiseError):
    """``--max-memory`` is below what the smallest useful tile of the model needs."""


def _mib(n: float) -> str:
    """Bytes rounded up to whole MiB, as ``--max-memory`` reads it (``"3M"``)."""
    return f"{math.ceil(n / (1 << 20))}M"


def _binary(n: float) -> str:
    """Bytes in the largest binary unit of ``--max-memory`` that fits (``"1K"``, ``"1.5G"``)."""
    for unit, suffix in ((1 << 30, "G"), (1 << 20, "M"), (1 << 10, "K")):
        if n >= unit:
            return f"{n / unit:.4g}{suffix}"
    return f"{int(n)}"


_COSTS: dict[tuple[str, str, int, str], MemoryCost] = {}


def default_device() -> torch.device:
    """CUDA when available, else the CPU."""
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def memory_cost(model: Denoiser, spp: int, device: torch.device) -> MemoryCost:
    """:func:`mcdenoise.infer.memory.measure_cost`, remembered per model configuration, spp and device."""
    key = (type(model).__qualname__, repr(getattr(model, "config", None)), spp, device.type)
    if key not in _COSTS:
        _COSTS[key] = measure_cost(model, spp, device, align=alignment(model))
    return _COSTS[key]


def tile_plan(model: Denoiser, height: int, width: int, *, spp: int = 1, device: torch.device | str = "cpu",
              tile: int | str | None = "auto", max_memory: int | None = None, reach: int = 0,
              held_outputs: int = 1) -> TilePlan:
    """The tile grid for ``model`` on an ``height x width`` image.

    ``tile``: ``"auto"``/None sizes tiles from ``max_memory`` (bytes, default 4 GiB) and the
    measured per-pixel cost; an int fixes the core side. The overlap is the measured receptive field
    plus ``reach`` (:func:`emitter_reach`: how far the fill of emitter pixels looks).
    ``held_outputs``: whole-image outputs held while a tile runs (a self-ensemble keeps one per
    orientation).
    """
    device = torch.device(device)
    if tile not in (None, "auto"):
        return plan_tiles(height, width, receptive=receptive_field(model) + reach, align=alignment(model),
                          core=int(tile))
    if height * width <= SMALL_IMAGE:
        return plan_tiles(height, width, receptive=0)  # one tile; nothing to measure
    total = max_memory or DEFAULT_MAX_MEMORY
    out_bytes = 3 * height * width * 4 * max(1, held_outputs)
    budget = total * BUDGET_FRACTION - out_bytes  # minus the outputs
    cost = memory_cost(model, spp, device)
    window = cost.max_pixels(budget)
    if height * width <= window:
        return plan_tiles(height, width, receptive=0)  # fits whole: the receptive field is not needed
    align = alignment(model)
    plan = plan_tiles(height, width, receptive=receptive_field(model) + reach, align=align, max_window_pixels=window)
    core = min(math.ceil(MIN_CORE / align) * align, max(height, width))
    if plan.core < core:
        side = core + 2 * plan.overlap
        need = (cost.bytes(side * side) + out_bytes) / BUDGET_FRACTION
        raise BudgetError(f"--max-memory {_binary(total)}: below the minimum for {type(model).__name__} on this "
                          f"{width}x{height} image: its smallest tile ({core} px + {plan.overlap} px overlap a side, "
                          f"{spp} spp) needs {_mib(need)}; give at least --max-memory {_mib(need)}, or --tile N")
    return plan


def emitter_reach(inputs: Inputs, names: list[str]) -> int:
    """Extra tile overlap for an image with emitter pixels (an albedo above 1 among the pixel
    buffers the model reads): their colour is filled from up to ``FILL_STEPS`` pixels away
    (:mod:`mcdenoise.models.emitters`), so a tile must see that much more to match the whole image.
    0 for images without (every image of our own renderer). Per-sample albedo is judged by the
    pixel means when the image has them."""
    from mcdenoise.models.emitters import ALBEDO_CHANNELS, FILL_STEPS

    wanted = [a for a in ALBEDO_CHANNELS if a in names]
    if not wanted:
        return 0
    inputs.ensure_pixels()
    if any(a in inputs.pixels and bool((inputs.pixels[a] > 1).any()) for a in wanted):
        return FILL_STEPS + 1
    return 0


@dataclass
class RunInfo:
    """How a denoise ran: the plan, the device, the input channels read."""

    plan: TilePlan
    device: torch.device
    channels: list[str]
    spp: int
    #: What the model's consistency clamp did (docs/models/consistency.md); "" for a model without one.
    consistency: str = ""
    #: Orientations run (8 for a self-ensemble, :mod:`mcdenoise.models.symmetry`; else 1).
    orientations: int = 1


def denoise_inputs(inputs: Inputs, model: Denoiser, *, device: torch.device | str | None = None,
                   tile: int | str | None = "auto", max_memory: int | None = None,
                   progress: bool | None = None, self_ensemble: bool = False) -> tuple[np.ndarray, RunInfo]:
    """Run ``model`` on ``inputs`` tile by tile -> ``(3, H, W)`` float32 linear radiance and a :class:`RunInfo`.

    ``progress``: a tqdm bar over tiles on stderr (None: only when stderr is a terminal).
    ``self_ensemble``: run the model on the image in each of the 8 orientations of
    :mod:`mcdenoise.models.symmetry` (each a whole tiled run of the turned image, so tiling stays
    exact) and keep the per-pixel median: 8x the time, 8 outputs held in memory.
    """
    device = torch.device(device) if device is not None else default_device()
    from mcdenoise.infer.oidn_method import OIDNMethod

    if isinstance(model, OIDNMethod):  # OIDN tiles by itself: the whole image, once
        add_oidn(inputs)
        inputs.warn_nonfinite()
        used = ["radiance", *oidn_guides(inputs.pixels)]
        return inputs.pixels["oidn"], RunInfo(plan_tiles(inputs.height, inputs.width, receptive=0), device, used, 1)
    model = model.to(device).eval()
    kind = model.input_kind
    spp = inputs.samples.spp if (kind == "samples" and inputs.samples is not None) else 1
    names = [c for c in model.required_channels() if c != "scene_features"]
    ops = ALL_OPS if self_ensemble else (0,)
    reach = emitter_reach(inputs, names)
    add_oidn(inputs, [n for n in names if n in OIDN_CHANNELS])
    scale = image_exposure(inputs, model, names, device)  # of the whole image: the same in every orientation
    outs, plan, counted = [], None, None
    for op in ops:
        h, w = turned_shape(inputs.height, inputs.width, op)
        plan = tile_plan(model, h, w, spp=spp, device=device, tile=tile, max_memory=max_memory, reach=reach,
                         held_outputs=len(ops))
        outs.append(untransform(_run_turned(inputs, model, names, kind, plan, op, scale, device, progress), op))
        if counted is None and inputs.samples is not None:
            counted = inputs.samples.nonfinite  # a file's samples count their NaNs at each read: once is the count
    if counted is not None:
        inputs.samples.nonfinite = counted
    assert plan is not None
    out = median_of(outs)
    del outs
    k = getattr(model.config, "consistency", None)
    first = getattr(model.config, "consistency_min_spp", 2)
    note = "" if k is None else f"each pixel within {k:g} standard errors of its own samples' mean"
    if kind == "samples" and k is not None and not acts_at(spp, first):
        note = f"not applied (consistency {k:g} acts from {max(2, first)} spp): the input has {spp}"
    if kind == "pixels" and k is not None:
        # On the whole image, after tiling (its 5x5 box would otherwise need the tiles' overlap).
        # The variance of the mean in noisy.exr is over every stored sample: the image folder's spp.
        n = inputs.samples.spp if inputs.samples is not None else 0
        var = inputs.pixels.get("radiance_variance")
        if var is None or n < 2:
            note = f"not applied (consistency {k:g}): the input has no per-pixel variance of its samples"
        elif not acts_at(n, first):
            note = f"not applied (consistency {k:g} acts from {max(2, first)} spp): the input has {n}"
        out = model.pixel_consistency(out, inputs.pixels.get("radiance"), var, n)
    inputs.warn_nonfinite()
    return out, RunInfo(plan, device, names, spp, note, len(ops))


def _run_turned(inputs: Inputs, model: Denoiser, names: list[str], kind: str, plan: TilePlan, op: int,
                scale: torch.Tensor | None, device: torch.device, progress: bool | None) -> np.ndarray:
    """``run_tiled`` over the image turned by op (``plan`` is the turned image's): each tile's
    window is read from the box of the image that op moves onto it, then turned."""
    def read(t: Any) -> dict[str, torch.Tensor]:
        window = source_box(t.window, op, inputs.height, inputs.width)
        core = source_box(t.core, op, inputs.height, inputs.width)
        b = transform_batch(inputs.batch(names, kind, window, core, device), op)
        if scale is not None:
            b[EXPOSURE_SCALE] = scale
        return b

    bar = None
    if progress is not False:
        from tqdm import tqdm

        desc = "denoise" if op == 0 else f"denoise, orientation {op + 1} of 8"

        def bar(tiles: Any) -> Any:
            return tqdm(tiles, total=len(plan), desc=desc, unit="tile", disable=None if progress is None else False,
                        leave=False)

    return run_tiled(model, read, plan, progress=bar)


def image_exposure(inputs: Inputs, model: Denoiser, names: list[str], device: torch.device) -> torch.Tensor | None:
    """``(1,)`` autoexposure scale of the whole image for a model that has autoexposure, so every
    tile is scaled alike (a tile's own scale would differ and leave seams); None otherwise. A
    sample model's is measured on the pixel means of its radiance, which is what it measures too."""
    if model.autoexposure is None:
        return None
    box = (0, 0, inputs.height, inputs.width)
    if model.input_kind == "pixels":
        whole = inputs.batch(names, "pixels", box, box, device)
    else:
        inputs.ensure_pixels()
        whole = {"radiance": torch.from_numpy(np.ascontiguousarray(inputs.pixels["radiance"]))[None].to(device)}
    with torch.no_grad():
        return model.exposure_of(whole)


def add_oidn(inputs: Inputs, channels: list[str] | tuple[str, ...] = ("oidn",)) -> None:
    """Put OIDN 2.5.1's outputs for the whole image into ``inputs.pixels[ch]`` for each derived
    channel ``ch`` (a combiner's candidates, see :data:`OIDN_CHANNELS`): run once on the full
    image, before tiling, as a user would run OIDN."""
    from mcdenoise.eval.oidn import oidn_denoise

    if not channels:
        return
    inputs.ensure_pixels()
    for ch in channels:
        if ch not in inputs.pixels:
            inputs.pixels[ch] = oidn_denoise(inputs.pixels["radiance"], **oidn_guides(inputs.pixels),
                                             prefilter=OIDN_CHANNELS[ch])


def describe_plan(plan: TilePlan) -> str:
    """``"1 tile"`` or ``"24 tiles of 512 px (+32 px overlap)"``."""
    n = len(plan)
    if n == 1:
        return "1 tile"
    return f"{n} tiles of {plan.core} px (+{plan.overlap} px overlap)"

