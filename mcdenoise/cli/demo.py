"""The showcase: render a built-in scene with depth of field at low spp, denoise it with the shipped
models and Open Image Denoise 2.5.1, and write EXRs, PNG previews and the HTML comparison.

Steps: (1) ``cornell-dof`` (default) at 8 spp plus a 1024-spp reference into ``OUT/render``,
reused on a rerun when its size, spp, reference spp and seed match the command; (2)
:func:`mcdenoise.eval.evaluate` on that image with every shipped model, OIDN ``high`` and ``fast``
and the NL-means filter, which writes ``OUT/report/index.html``, ``results.json`` and the full-size
outputs; (3) the EXRs and a tonemapped PNG of each output under ``OUT/exr`` and ``OUT/png``; (4) the
ranked summary ``mcdenoise eval`` prints (:func:`mcdenoise.eval.ranking.terminal_summary`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path


def add_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    p.add_argument("--scene", default="cornell-dof", help="built-in scene or scene file (default cornell-dof)")
    p.add_argument("--size", type=int, default=128, help="square image size in pixels (default 128)")
    p.add_argument("--spp", type=int, default=8, help="input samples per pixel (default 8)")
    p.add_argument("--ref-spp", type=int, default=1024, help="reference samples per pixel (default 1024)")
    p.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    p.add_argument("--models", nargs="*", help="models to run (default: every shipped model)")
    p.add_argument("--rerender", action="store_true", help="render again even if a matching render exists")


def _say(msg: str) -> None:
    print(msg, flush=True)


def _matches(folder: Path, args: argparse.Namespace) -> bool:
    """True when ``folder`` holds a finished render made with this command's settings."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError):
        return False
    return (meta.get("width"), meta.get("height"), meta.get("spp"), meta.get("reference_spp"), meta.get("seed")) == \
        (args.size, args.size, args.spp, args.ref_spp, args.seed) and (folder / "reference.exr").is_file()


def _render(args: argparse.Namespace, folder: Path) -> float:
    from mcdenoise.render import RenderSettings, builtin_motion, list_builtin_scenes, load_scene, render_image

    extra = builtin_motion(args.scene) if args.scene in list_builtin_scenes() else {}
    settings = RenderSettings(spp=args.spp, ref_spp=args.ref_spp, width=args.size, height=args.size,
                              seed=args.seed, **extra)
    settings.check()
    t0 = time.perf_counter()
    scene = load_scene(args.scene, width=args.size, height=args.size)
    render_image(scene, folder, settings, scene_name=Path(args.scene).stem, overwrite=True, progress=True)
    return time.perf_counter() - t0


def run(args: argparse.Namespace) -> int:
    from mcdenoise.errors import McDenoiseError
    from mcdenoise.eval import evaluate
    from mcdenoise.eval.oidn import oidn_available
    from mcdenoise.eval.ranking import terminal_summary
    from mcdenoise.io.exr import read_exr, write_preview
    from mcdenoise.models.weights import shipped

    if args.size < 16:
        raise McDenoiseError(f"demo: --size {args.size} is too small to show anything; use 16 or more")
    if args.spp < 1 or args.ref_spp < 1:
        raise McDenoiseError("demo: --spp and --ref-spp must be >= 1 (the report needs a reference)")
    t_start = time.perf_counter()
    out: Path = args.out
    folder = out / "render" / Path(args.scene).stem
    # Every shipped model: `small` presets by name, others (the ens combiner) by their weights file
    models = args.models if args.models is not None else [s.name if s.preset == "small" else str(s.weights)
                                                           for s in shipped()]

    if _matches(folder, args) and not args.rerender:
        _say(f"[1/3] render: reusing {folder} (same size, spp, reference spp and seed; --rerender renders again)")
    else:
        _say(f"[1/3] render: {args.scene}, {args.size}x{args.size}, {args.spp} spp + {args.ref_spp}-spp reference ...")
        if folder.exists() and (folder / "meta.json").is_file():
            shutil.rmtree(folder)  # our own earlier render with other settings
        secs = _render(args, folder)
        _say(f"      wrote {folder} in {secs:.1f} s (includes Mitsuba's kernel compilation)")

    if not models:
        _say("      no shipped weights found: only the baselines run (see docs/TRAINING.md)")
    if not oidn_available():
        _say("      Open Image Denoise is not installed (pip install pyoidn==2.5.1.0): OIDN rows skipped")
    _say(f"[2/3] denoise and score: {', '.join(models) or 'no models'}, OIDN high and fast, NL-means ...")
    report = out / "report"
    doc = evaluate(models=models, data=[folder], out=report, spp=[args.spp],
                   oidn=("high", "fast") if oidn_available() else (), threads=1, save_images=True, progress=True,
                   command=f"mcdenoise demo --scene {args.scene} --size {args.size} --spp {args.spp} "
                           f"--ref-spp {args.ref_spp} --seed {args.seed}")

    _say(f"[3/3] EXRs and previews ({args.spp} spp input; relMSE against the {args.ref_spp}-spp reference):")
    image_dir = next((report / "images").iterdir())
    exr_dir, png_dir = out / "exr", out / "png"
    for d in (exr_dir, png_dir):
        if d.exists():
            shutil.rmtree(d)
        d.mkdir(parents=True)
    sources = {"reference": image_dir / "reference.exr",
               **{p.stem: p for p in sorted((image_dir / f"{args.spp}spp").glob("*.exr"))}}
    for name, src in sources.items():
        shutil.copyfile(src, exr_dir / src.name)
        write_preview(png_dir / f"{name}.png", read_exr(src)["radiance"], tonemap="reinhard")
    _say(terminal_summary(doc))  # the ranked summary `mcdenoise eval` prints
    rows = {r["method"]: r["relmse"] for r in doc["summary"] if r["subset"] == "all" and r["spp"] == args.spp}
    worse = [m for m in models if m in rows and "noisy" in rows and rows[m] > rows["noisy"]]
    if worse:
        _say(f"note: {', '.join(worse)} end up worse than the noisy input here: their kernels blur the visible "
             "light onto the dark ceiling, and those pixels dominate relMSE (docs/RESULTS.md)")
    _say(f"report: {report / 'index.html'}")
    _say(f"EXRs:   {exr_dir}/  PNGs: {png_dir}/  (tonemapped with Reinhard)")
    _say(f"done in {time.perf_counter() - t_start:.0f} s")
    return 0
