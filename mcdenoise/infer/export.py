"""Export a denoiser for use outside Python: ONNX (onnxruntime, C++ hosts) or TorchScript (libtorch).

The exported graph takes the model's input channels as positional tensors, in the order of
:func:`input_names` (``required_channels()``, then ``scene_features`` for the sample models):
pixel models read ``(1, C, H, W)`` float32 each, sample models ``(1, S, C, H, W)`` plus
``scene_features (1, 5)``; the output is ``(1, 3, H, W)`` linear radiance. The names and shapes
are also written next to the file as ``<file>.json``.

Export runs the model in inference mode, so shape-dependent Python (row bands, padding) is
recorded for the example size; :func:`export_model` checks the exported file against PyTorch on
the example size (must match, else no file) and on other sizes and sample counts. An exported file
either works at every size and spp it accepts or refuses the others: when the other sizes differ,
a TorchScript file is exported again with a shape check on every input (a scripted function the
trace calls, so it runs in the file) and an ONNX file keeps its static shapes; ``<file>.json``
then gives the fixed ``H``, ``W`` and ``S``. A model with an op an exporter cannot translate is
refused in one line that names the op.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, List

import torch
from torch import nn

from mcdenoise.errors import McDenoiseError
from mcdenoise.io.atomic import atomic_file
from mcdenoise.models.registry import Denoiser, synthetic_batch
from mcdenoise.ops import use_impl

__all__ = ["FORMATS", "ExportError", "input_names", "ExportWrapper", "export_model", "run_exported"]

FORMATS = ("onnx", "torchscript")
#: Relative tolerance of the check of an exported file against PyTorch (float32 reassociation).
CHECK_RTOL = 1e-4


class ExportError(McDenoiseError):
    """A model cannot be exported to the format asked for."""


def input_names(model: Denoiser) -> list[str]:
    """Positional inputs of the exported graph, in order."""
    names = [c for c in model.required_channels() if c != "scene_features"]
    return names + (["scene_features"] if model.input_kind == "samples" else [])


_GUARD: Any = None


def _shape_guard() -> Any:
    """A scripted ``(x, shape, name) -> x`` that raises unless ``x`` has exactly ``shape``; called
    inside a trace it stays a call in the exported graph, so the check runs in the file itself."""
    global _GUARD
    if _GUARD is None:
        def expect_shape(x: torch.Tensor, shape: List[int], name: str) -> torch.Tensor:
            if x.shape != shape:
                raise RuntimeError("mcdenoise export: input " + name + " must have shape " + str(shape) + ", got "
                                   + str(x.shape) + " (this file was exported for that window size and spp only)")
            return x

        _GUARD = torch.jit.script(expect_shape)
    return _GUARD


class ExportWrapper(nn.Module):
    """Positional tensors -> the model's batch dict -> ``(1, 3, H, W)`` (exporters want positional inputs).

    ``shapes``: the exact shape of each input, checked in the exported file (None: unchecked).
    """

    def __init__(self, model: Denoiser, shapes: list[list[int]] | None = None) -> None:
        super().__init__()
        self.model = model
        self.names = input_names(model)
        self.shapes = shapes

    def forward(self, *tensors: torch.Tensor) -> torch.Tensor:
        if self.shapes is not None:
            guard = _shape_guard()
            tensors = tuple(guard(t, s, n) for t, s, n in zip(tensors, self.shapes, self.names))
        return self.model(dict(zip(self.names, tensors)))


def _example(model: Denoiser, height: int, width: int, spp: int, seed: int) -> tuple[torch.Tensor, ...]:
    batch = synthetic_batch(model, spp=spp, height=height, width=width, generator=torch.Generator().manual_seed(seed))
    return tuple(batch[n] for n in input_names(model))


def _op_of(exc: BaseException) -> str:
    """The operator an exporter choked on, from its message, else the message's first line."""
    text = str(exc)
    for pat in (r"(aten::[A-Za-z0-9_.]+)", r"(aten\.[A-Za-z0-9_.]+)", r"operator '?([A-Za-z0-9_:.]+)'?"):
        m = re.search(pat, text)
        if m:
            return m.group(1)
    first = text.strip().splitlines()
    return (first[0] if first else type(exc).__name__)[:200]


def run_exported(path: str | os.PathLike, fmt: str, inputs: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """Run an exported file on ``inputs`` with onnxruntime (CPU) or torch.jit -> ``(1, 3, H, W)``."""
    if fmt == "onnx":
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.log_severity_level = 3  # errors come back as exceptions; no log lines on stderr
        sess = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        feed = {i.name: t.numpy() for i, t in zip(sess.get_inputs(), inputs)}
        return torch.from_numpy(sess.run(None, feed)[0])
    mod = torch.jit.load(str(path))
    with torch.no_grad():
        return mod(*inputs)


def _compare(model: Denoiser, names: list[str], path: Path, fmt: str,
             inputs: tuple[torch.Tensor, ...]) -> float | None:
    """Max relative difference of the exported file from PyTorch on ``inputs`` (None: it failed)."""
    with torch.no_grad():
        want = model(dict(zip(names, inputs)))
    try:
        got = run_exported(path, fmt, inputs)
    except Exception:  # onnxruntime and the TorchScript interpreter raise their own types
        return None
    if got.shape != want.shape:
        return None
    return float((got - want).abs().max() / want.abs().max().clamp_min(1e-12))


def _write_onnx(wrapper: ExportWrapper, example: tuple[torch.Tensor, ...], tmp: Path, sample: bool) -> None:
    """ONNX through torch.export (opset 18), specialised to the example's shapes; the check after
    export finds out whether the file also runs at other sizes."""
    import contextlib
    import io

    # The exporter prints its progress and, on failure, whole graphs: keep the CLI's one line.
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        prog = torch.onnx.export(wrapper, example, input_names=wrapper.names, output_names=["radiance_out"],
                                 opset_version=18, dynamo=True, verbose=False)
        prog.save(str(tmp))


def _export(model: Denoiser, wrapper: ExportWrapper, example: tuple[torch.Tensor, ...], tmp: Path, fmt: str,
            sample: bool) -> None:
    try:
        # The plain-PyTorch references: the fast paths are custom autograd Functions,
        # which exporters cannot see into.
        with torch.no_grad(), use_impl("reference"):
            if fmt == "torchscript":
                traced = torch.jit.trace(wrapper, example, check_trace=False)
                traced.save(str(tmp))
            else:
                _write_onnx(wrapper, example, tmp, sample)
    except Exception as e:  # exporters raise many types; all mean "this op does not export"
        raise ExportError(f"{type(model).__name__} cannot be exported to {fmt}: unsupported op {_op_of(e)}") from None


def _check_same(model: Denoiser, names: list[str], tmp: Path, fmt: str, inputs: tuple[torch.Tensor, ...]) -> float:
    """The exported file on the export's own shapes, new data: must match PyTorch."""
    err = _compare(model, names, tmp, fmt, inputs)
    if err is None or not err <= CHECK_RTOL:
        what = "fails" if err is None else f"differs from PyTorch (relative error {err:.2e})"
        raise ExportError(f"{type(model).__name__}: the exported {fmt} file {what} on a sample input")
    return err


def export_model(model: Denoiser, path: str | os.PathLike, fmt: str, *, example_size: tuple[int, int] = (128, 128),
                 spp: int = 4) -> dict[str, Any]:
    """Export ``model`` to ``path`` (atomically) and check it against PyTorch on another size.

    Returns the description also written to ``<path>.json`` (inputs, shapes, check error).
    Raises :class:`ExportError` naming the op when the exporter fails or the check does not hold.
    """
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")
    model = model.cpu().eval()
    wrapper = ExportWrapper(model).eval()
    sample = model.input_kind == "samples"
    example = _example(model, *example_size, spp, seed=0)
    path = Path(path)
    h, w = example_size
    # Other sizes and sample counts the file must either match PyTorch on or refuse.
    others = [_example(model, h + 13, w + 7, max(1, spp - 1), seed=2), _example(model, h, w, spp + 1, seed=3),
              _example(model, h + 5, w + 3, spp, seed=4)]
    if not sample:
        others = others[::2]
    with atomic_file(path) as tmp:
        _export(model, wrapper, example, tmp, fmt, sample)
        # Check 1, must hold: the export's own size and sample count, new data.
        err = _check_same(model, wrapper.names, tmp, fmt, _example(model, h, w, spp, seed=1))
        # Check 2, decides what the file promises: other sizes and sample counts.
        errs = [_compare(model, wrapper.names, tmp, fmt, o) for o in others]
        dynamic = all(e is not None and e <= CHECK_RTOL for e in errs)
        if not dynamic and fmt == "torchscript":
            # Frozen at the example's shapes but silently wrong elsewhere: export again with a
            # shape check on every input, then make sure it holds.
            guarded = ExportWrapper(model, [list(t.shape) for t in example]).eval()
            _export(model, guarded, example, tmp, fmt, sample)
            err = _check_same(model, wrapper.names, tmp, fmt, _example(model, h, w, spp, seed=1))
            if any(_compare(model, wrapper.names, tmp, fmt, o) is not None for o in others):
                raise ExportError(f"{type(model).__name__}: the exported {fmt} file does not refuse other sizes")
    fixed = not dynamic
    hh, ww, ss = (str(h), str(w), str(spp)) if fixed else ("H", "W", "S")
    desc = {
        "format": fmt,
        "inputs": [{"name": n, "shape": ["1", ss, str(t.shape[2]), hh, ww] if (sample and n != "scene_features")
                    else ["1", str(t.shape[1]), hh, ww] if n != "scene_features" else ["1", str(t.shape[1])]}
                   for n, t in zip(wrapper.names, example)],
        "output": {"name": "radiance_out", "shape": ["1", "3", hh, ww]},
        "check_relative_error": err,
        # False: shape-dependent Python (padding, row bands) was frozen at export; feed windows of
        # exactly this size and sample count (tile the image with mcdenoise's overlap).
        "any_size": dynamic,
        "size": list(example_size),
        "spp": spp if sample else None,
    }
    with atomic_file(path.with_name(path.name + ".json")) as tmp:
        tmp.write_text(json.dumps(desc, indent=1) + "\n")
    return desc
