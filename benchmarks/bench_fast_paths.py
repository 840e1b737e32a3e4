"""The measurements behind the fast-path table of docs/PERFORMANCE.md ("Fast inference paths").

    .venv/bin/python benchmarks/bench_fast_paths.py                     # every part
    .venv/bin/python benchmarks/bench_fast_paths.py --parts pointwise unet

Parts (each prints a Markdown table; medians of ``--repeats`` interleaved calls after warm-up):

* ``pointwise``: a 1x1 convolution, oneDNN ``F.conv2d`` against :class:`PointwiseConv`
  (``baddbmm``), at the per-sample shapes of SBMC/layer small (8 samples, 480x270).
* ``convs``: one 5x5 convolution of WSKP's and KPCN's widths at 1920x1080, float32 NCHW, float32
  channels_last and bfloat16 channels_last.
* ``layout``: :func:`convert_layout` against a plain ``.to(dtype, memory_format=...)`` for KPCN's
  trunk input (27 channels, to bfloat16 channels_last) and logits (81 channels, back) at 1080p.
* ``unet``: one U-Net of ``layer_optimized``, ``layer`` and ``sbmc`` small alone at 1080p,
  float32 against its bfloat16 trunk form (separates precision from the per-sample work, whose
  run-to-run spread is large).
* ``combine``: the combiner's pieces at 1080p that campaign 11 sped up: the noisy clamp's 3x3
  maximum (``max_pool2d`` of the replicate-padded image against :func:`max3x3`), and the ``own``
  preset's 1x1 head on a bfloat16 channels_last trunk output (16 -> 52 and 24 -> 52 channels:
  the NCHW reshape + ``baddbmm`` path :class:`PointwiseConv` took before against the oneDNN
  convolution it now leaves NHWC input to).
* ``consistency``: the sample models' consistency clamp (:mod:`mcdenoise.models.consistency`) at
  1080p and 4 / 8 / 16 spp, with the variance from ``torch.var_mean`` over the sample axis (before)
  against the two written-out passes it uses.
* ``precision``: whole models, float32 against bfloat16 trunks, at 1280x720 and 8 spp.
* ``thp``: whole models in child processes with ``THP_MEM_ALLOC_ENABLE`` 1 and 0 (huge pages
  are chosen once per process), median of the calls after two warm-ups.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import subprocess
import sys

import _timing  # noqa: F401  (puts the repository on sys.path)
import torch
import torch.nn.functional as F

from mcdenoise.bench.plan import parse_method
from mcdenoise.bench.timing import interleaved_times
from mcdenoise.models.blocks import PointwiseConv, UNet
from mcdenoise.models.inference import ReducedPrecision, convert_layout, inference_context, prepare_inference
from mcdenoise.models.registry import build_model, synthetic_batch

CL = torch.channels_last


def _medians(fns: dict, repeats: int) -> dict[str, float]:
    for fn in fns.values():  # warm-up
        fn()
    return {k: statistics.median(v) * 1e3 for k, v in interleaved_times(fns, repeats).items()}


def part_pointwise(repeats: int) -> None:
    print("| C_in -> C_out (8 x 480x270) | conv2d ms | PointwiseConv ms | speed-up |\n|---|---:|---:|---:|")
    for ci, co in ((16, 16), (16, 121), (42, 16), (8, 8), (8, 28)):
        conv = PointwiseConv(ci, co)
        x = torch.randn(8, ci, 270, 480)
        with torch.inference_mode():
            t = _medians({"conv": lambda: F.conv2d(x, conv.weight, conv.bias), "pw": lambda: conv(x)}, repeats)
        print(f"| {ci} -> {co} | {t['conv']:.1f} | {t['pw']:.1f} | {t['conv'] / t['pw']:.1f}x |", flush=True)


def part_convs(repeats: int) -> None:
    print("| 5x5 conv at 1920x1080 | fp32 NCHW ms | fp32 channels_last ms | bf16 channels_last ms | bf16 CL GFLOP/s |")
    print("|---|---:|---:|---:|---:|")
    for ci, co in ((10, 14), (14, 14), (27, 24), (24, 24), (24, 81)):
        x, w, b = torch.randn(1, ci, 1080, 1920), torch.randn(co, ci, 5, 5) * 0.1, torch.zeros(co)
        xc, wc = x.contiguous(memory_format=CL), w.contiguous(memory_format=CL)
        xb, wb, bb = x.to(torch.bfloat16, memory_format=CL), w.to(torch.bfloat16, memory_format=CL), b.bfloat16()
        with torch.inference_mode():
            t = _medians({"f32": lambda: F.conv2d(x, w, b, padding=2), "f32cl": lambda: F.conv2d(xc, wc, b, padding=2),
                          "bf16cl": lambda: F.conv2d(xb, wb, bb, padding=2)}, repeats)
        gflops = 2 * ci * co * 25 * 1080 * 1920 / (t["bf16cl"] * 1e-3) / 1e9
        print(f"| {ci} -> {co} | {t['f32']:.0f} | {t['f32cl']:.0f} | {t['bf16cl']:.0f} | {gflops:.0f} |", flush=True)


def part_layout(repeats: int) -> None:
    print("| copy at 1920x1080 | plain .to() ms | convert_layout ms |\n|---|---:|---:|")
    x = torch.randn(1, 27, 1080, 1920)
    y = torch.randn(1, 81, 1080, 1920).to(torch.bfloat16, memory_format=CL)
    with torch.inference_mode():
        for label, t_in, dtype, fmt in (("27 ch float32 NCHW -> bfloat16 channels_last", x, torch.bfloat16, CL),
                                        ("81 ch bfloat16 channels_last -> float32 NCHW", y, torch.float32,
                                         torch.contiguous_format)):
            t = _medians({"to": lambda: t_in.to(dtype, memory_format=fmt),
                          "banded": lambda: convert_layout(t_in, dtype, fmt)}, repeats)
            print(f"| {label} | {t['to']:.0f} | {t['banded']:.0f} |", flush=True)


def part_unet(repeats: int) -> None:
    print("| U-Net of (small) at 1920x1080 | float32 ms | bfloat16 trunk ms |\n|---|---:|---:|")
    for name in ("layer_optimized", "layer", "sbmc"):
        unet = next(m for m in build_model(name, "small").eval().modules() if isinstance(m, UNet))
        low = ReducedPrecision(copy.deepcopy(unet))
        x = torch.randn(1, unet.enc[0][0].in_channels, 1080, 1920)
        kw = {"return_decoder": True} if name == "layer_optimized" else {}
        with torch.inference_mode():
            t = _medians({"f32": lambda: unet(x, **kw), "bf16": lambda: low(x, **kw)}, repeats)
        print(f"| {name} | {t['f32']:.0f} | {t['bf16']:.0f} |", flush=True)


def _model_call(label: str, w: int, h: int, spp: int, precision: str) -> tuple[torch.nn.Module, dict]:
    m = parse_method(label)
    torch.manual_seed(0)
    model = prepare_inference(build_model(m.name, m.preset), precision=precision)
    return model, synthetic_batch(model, spp=spp, height=h, width=w, generator=torch.Generator().manual_seed(1))


def part_precision(repeats: int, models: list[str]) -> None:
    print("| model at 1280x720, 8 spp | float32 ms | bfloat16 trunks ms | ratio |\n|---|---:|---:|---:|")
    for label in models:
        f32, batch = _model_call(label, 1280, 720, 8, "float32")
        bf16, _ = _model_call(label, 1280, 720, 8, "bfloat16")
        with inference_context(True):
            f32(batch)
            bf16(batch)
            t = _medians({"f32": lambda: f32(batch), "bf16": lambda: bf16(batch)}, repeats)
        print(f"| {label} | {t['f32']:.0f} | {t['bf16']:.0f} | {t['bf16'] / t['f32']:.2f} |", flush=True)


def part_thp(repeats: int, models: list[str], size: str) -> None:
    print(f"| model at {size}, 8 spp, precision auto | THP_MEM_ALLOC_ENABLE=1 ms | =0 ms |\n|---|---:|---:|")
    for label in models:
        got = {}
        for flag in ("1", "0"):
            cmd = [sys.executable, __file__, "--child", label, size, str(repeats)]
            out = subprocess.run(cmd, env={**os.environ, "THP_MEM_ALLOC_ENABLE": flag}, capture_output=True,
                                 text=True, check=True).stdout
            got[flag] = float(out.split()[-1])
        print(f"| {label} | {got['1']:.0f} | {got['0']:.0f} |", flush=True)


def _child(label: str, size: str, repeats: int) -> None:
    w, h = (int(v) for v in size.split("x"))
    model, batch = _model_call(label, w, h, 8, "auto")
    with inference_context(True):
        model(batch)  # first of two warm-ups; _medians makes the second
        print(_medians({"m": lambda: model(batch)}, repeats)["m"])


def part_combine(repeats: int) -> None:
    from mcdenoise.models.combine import max3x3

    print("| piece at 1920x1080 | before ms | now ms | speed-up |\n|---|---:|---:|---:|")
    x = torch.rand(1, 3, 1080, 1920)
    with torch.inference_mode():
        t = _medians({"before": lambda: F.max_pool2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), 3, stride=1),
                      "now": lambda: max3x3(x)}, repeats)
        print(f"| 3x3 maximum, 3 ch float32 | {t['before']:.0f} | {t['now']:.0f} | {t['before'] / t['now']:.1f}x |", flush=True)
        for ci in (16, 24):
            head = PointwiseConv(ci, 52).to(torch.bfloat16)
            y = torch.randn(1, ci, 1080, 1920).to(torch.bfloat16, memory_format=CL)
            wt = head.weight.view(52, ci).unsqueeze(0)
            t = _medians({"before": lambda: torch.baddbmm(head.bias.view(1, -1, 1), wt, y.reshape(1, ci, -1)),
                          "now": lambda: head(y)}, repeats)
            print(f"| 1x1 head {ci} -> 52, bfloat16 channels_last | {t['before']:.0f} | {t['now']:.0f} | "
                  f"{t['before'] / t['now']:.1f}x |", flush=True)


def part_consistency(repeats: int) -> None:
    from mcdenoise.models import consistency

    print("| spp at 1920x1080 | var_mean ms | now ms | speed-up |\n|---|---:|---:|---:|")
    out = torch.rand(1, 3, 1080, 1920)

    def before(x: torch.Tensor) -> torch.Tensor:  # the first version: one var_mean over the sample axis
        var, mean = torch.var_mean(x, dim=1, correction=1)
        return var + mean

    for spp in (4, 8, 16):
        x = torch.rand(1, spp, 3, 1080, 1920)
        with torch.inference_mode():
            t = _medians({"before": lambda: before(x), "now": lambda: consistency.consistency_clamp(out, x, 2.0)},
                         repeats)
        print(f"| {spp} | {t['before']:.0f} | {t['now']:.0f} | {t['before'] / t['now']:.1f}x |", flush=True)


PARTS = ("pointwise", "convs", "layout", "unet", "combine", "consistency", "precision", "thp")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--models", nargs="+", default=["wskp:paper", "kpcn", "layer_optimized", "sbmc"])
    ap.add_argument("--thp-size", default="1920x1080")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        _child(args.child[0], args.child[1], int(args.child[2]))
        return
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, load average {os.getloadavg()[0]:.2f}")
    for part in args.parts:
        print(f"\n### {part}\n")
        if part == "precision":
            part_precision(args.repeats, args.models)
        elif part == "thp":
            part_thp(args.repeats, args.models, args.thp_size)
        else:
            globals()[f"part_{part}"](args.repeats)


if __name__ == "__main__":
    main()
