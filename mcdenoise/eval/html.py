"""The static HTML page of ``mcdenoise eval``: tables, a plot, and side-by-side crops per image.

No scripts and nothing fetched from the network: ``index.html`` references only PNGs beside it.

* ``index.html`` leads with the ranked summary of :mod:`mcdenoise.eval.ranking` (per spp, best
  relMSE first, best of each column in bold, ratio to OIDN high), then the plot, every metric's
  mean, and the crops (one table per image: a row per spp, a column per method). The
  depth-of-field / motion-blur subset gets its own tables only when it is not every image.
* ``relmse_vs_spp.png``: mean relMSE (log axis) against spp (log2 axis, one tick per spp), one
  colour and marker per method; with one spp a bar per method, best first. A second panel for
  the depth-of-field / motion-blur subset when it has images and is not every image.
* ``img/<image>/``: per image a crop window (the whole image up to :data:`CROP` pixels a side,
  else the window where the noisy input at the lowest spp has the largest relMSE), then for
  every spp and method the tonemapped crop (``mcdenoise.eval.metrics.tonemap``, ``reinhard``)
  and its per-pixel relMSE map ``mean_c (x - y)^2 / (y^2 + 0.01)`` coloured with matplotlib's
  ``inferno`` on a fixed log scale (:data:`ERR_RANGE`), and the reference crop.
* ``error_legend.png``: the colour bar of the error maps.
"""

from __future__ import annotations

import html
import re
from pathlib import Path
from typing import Any

import numpy as np

from mcdenoise.eval.metrics import tonemap
from mcdenoise.eval.seeds import spread_text
from mcdenoise.io.exr import write_png

__all__ = ["CROP", "ERR_RANGE", "CropWriter", "write_report", "relmse_map"]

#: Largest crop edge in pixels.
CROP = 128
#: relMSE values mapped to the ends of the colour map (log scale).
ERR_RANGE = (1e-4, 1e1)
_CMAP = "inferno"
#: Columns of the means table beyond method and spp, with their headers (metric names added).
_LOWER_BETTER = {"mse", "relmse", "smape", "l1", "rel_l1", "dssim", "flip"}


def relmse_map(x: np.ndarray, y: np.ndarray, eps: float = 1e-2) -> np.ndarray:
    """Per-pixel relMSE, (3, H, W) x2 -> (H, W), the same formula as :func:`metrics.relmse`."""
    x64, y64 = np.asarray(x, np.float64), np.asarray(y, np.float64)
    return ((x64 - y64) ** 2 / (y64 ** 2 + eps)).mean(axis=0)


def _lut() -> np.ndarray:
    from matplotlib import colormaps

    return (np.asarray(colormaps[_CMAP](np.linspace(0.0, 1.0, 256))[:, :3]) * 255.0 + 0.5).astype(np.uint8)


def _err_png(err: np.ndarray, lut: np.ndarray) -> np.ndarray:
    lo, hi = np.log10(ERR_RANGE[0]), np.log10(ERR_RANGE[1])
    t = (np.log10(np.maximum(np.nan_to_num(err, nan=ERR_RANGE[1], posinf=ERR_RANGE[1]), 1e-30)) - lo) / (hi - lo)
    return lut[np.clip(np.round(t * 255.0), 0, 255).astype(np.int64)]


def _ldr(rgb: np.ndarray) -> np.ndarray:
    """(3, H, W) linear radiance -> (H, W, 3) uint8, reinhard tonemap (NaN shown black)."""
    t = tonemap(np.nan_to_num(np.asarray(rgb, np.float64), nan=0.0, posinf=1e6, neginf=0.0), "reinhard")
    return np.round(np.asarray(t) * 255.0).astype(np.uint8).transpose(1, 2, 0)


def _window(err: np.ndarray, size: int) -> tuple[int, int, int, int]:
    """(y0, x0, h, w): the size x size window with the largest summed ``err`` (whole image when small)."""
    h, w = err.shape
    ch, cw = min(size, h), min(size, w)
    if (ch, cw) == (h, w):
        return 0, 0, h, w
    c = np.pad(np.nan_to_num(err).cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    sums = c[ch:, cw:] - c[:-ch, cw:] - c[ch:, :-cw] + c[:-ch, :-cw]
    y0, x0 = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(y0), int(x0), ch, cw


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_.") or "x"


class CropWriter:
    """Writes the crops and error maps of each (image, spp) as the evaluation goes."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.lut = _lut()
        #: image id -> {"dir", "window", "ref", "cells": {spp: {method: (png, err_png)}}}
        self.entries: dict[str, dict[str, Any]] = {}
        self._dirs: set[str] = set()

    def add(self, image: str, spp: int, outputs: dict[str, np.ndarray], ref: np.ndarray) -> None:
        """``outputs``: method -> (3, H, W) radiance (``noisy`` first); ``ref`` (3, H, W)."""
        e = self.entries.get(image)
        if e is None:
            d = _safe(image)
            n = 2
            while d in self._dirs:
                d, n = f"{_safe(image)}-{n}", n + 1
            self._dirs.add(d)
            noisy = outputs.get("noisy", next(iter(outputs.values())))
            win = _window(relmse_map(noisy, ref), CROP)
            e = {"dir": d, "window": win, "ref": f"img/{d}/reference.png", "cells": {}}
            (self.root / "img" / d).mkdir(parents=True, exist_ok=True)
            write_png(self.root / e["ref"], _ldr(self._crop(ref, win)))
            self.entries[image] = e
        win, d = e["window"], e["dir"]
        cells: dict[str, tuple[str, str]] = {}
        rc = self._crop(ref, win)
        for name, y in outputs.items():
            stem = f"img/{d}/{spp:05d}spp_{_safe(name)}"
            yc = self._crop(y, win)
            write_png(self.root / f"{stem}.png", _ldr(yc))
            write_png(self.root / f"{stem}_err.png", _err_png(relmse_map(yc, rc), self.lut))
            cells[name] = (f"{stem}.png", f"{stem}_err.png")
        e["cells"][spp] = cells

    @staticmethod
    def _crop(x: np.ndarray, win: tuple[int, int, int, int]) -> np.ndarray:
        y0, x0, h, w = win
        return x[:, y0:y0 + h, x0:x0 + w]


#: Marker shapes cycled beside the colours, so methods stay apart in grey print and when colours repeat.
_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<", ">", "*")


def _panels(summary: list[dict[str, Any]], same: bool) -> list[tuple[str, str]]:
    """(subset, title) of each plot panel: all images, and the DoF / motion subset when it differs."""
    out = [("all", "all images")]
    if not same and any(s["subset"] == "dof_motion" for s in summary):
        out.append(("dof_motion", "depth-of-field / motion-blur images"))
    return out


def _plot(path: Path, summary: list[dict[str, Any]], methods: list[str], same: bool = False) -> None:
    """Mean relMSE per method: against spp (one x per spp, log axes) when there are several,
    else a bar per method, best first. One panel per subset, one colour and marker per method
    (the same in every panel), one legend."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = _panels(summary, same)
    spps = sorted({s["spp"] for s in summary if s.get("relmse") is not None})
    from matplotlib.ticker import FuncFormatter, LogLocator

    # tab10's ten distinct colours, then its lighter twins; the marker changes with the colour.
    colours = [plt.get_cmap("tab10")(i) for i in range(10)] + [plt.get_cmap("tab20")(2 * i + 1) for i in range(10)]
    style = {m: (colours[i % 20], _MARKERS[i % len(_MARKERS)]) for i, m in enumerate(methods)}
    n = len(panels)
    label_w = 0.075 * max([len(m) for m in methods] + [8]) + 0.6  # inches the legend needs on the right
    if len(spps) >= 2:
        fig, axes = plt.subplots(1, n, figsize=(5.0 * n + label_w, 4.4), dpi=100, sharey=True, squeeze=False)
        for ax, (subset, title) in zip(axes[0], panels):
            for i, m in enumerate(methods):
                pts = sorted((s["spp"], s["relmse"]) for s in summary
                             if s["method"] == m and s["subset"] == subset and s.get("relmse") is not None)
                if not pts:
                    continue
                # A small sideways offset per method, so equal values do not hide each other.
                shift = 2.0 ** (0.12 * (i - (len(methods) - 1) / 2) / max(1, len(methods) - 1))
                colour, marker = style[m]
                ax.plot([k * shift for k, _ in pts], [v for _, v in pts], "-", marker=marker, color=colour,
                        label=m, ms=6, lw=1.4)
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.yaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
            ax.set_xticks(spps)
            ax.set_xticklabels([str(k) for k in spps])
            ax.minorticks_off()
            ax.set_xlabel("input samples per pixel")
            ax.set_title(title, fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
        axes[0][0].set_ylabel("mean relMSE (lower is better)")
        handles, labels = axes[0][0].get_legend_handles_labels()
    else:
        fig, axes = plt.subplots(1, n, figsize=(5.6 * n, 0.9 + 0.32 * len(methods)), dpi=100, squeeze=False)
        for ax, (subset, title) in zip(axes[0], panels):
            vals = sorted(((s["relmse"], s["method"]) for s in summary
                           if s["subset"] == subset and s.get("relmse") is not None), reverse=True)
            ys = range(len(vals))
            ax.barh(list(ys), [v for v, _ in vals], color=[style[m][0] for _, m in vals])
            ax.set_yticks(list(ys))
            ax.set_yticklabels([m for _, m in vals], fontsize=9)
            for y, (v, _) in zip(ys, vals):
                ax.text(v, y, f" {v:.3g}", va="center", fontsize=8)
            ax.set_xscale("log")
            if vals:
                ax.set_xlim(min(v for v, _ in vals) / 2, max(v for v, _ in vals) * 2.5)
            ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            ax.xaxis.set_minor_formatter(FuncFormatter(lambda v, _: ""))
            ax.set_xlabel(f"mean relMSE at {spps[0] if spps else '?'} spp (lower is better)")
            ax.set_title(title, fontsize=10)
            ax.grid(True, axis="x", which="both", alpha=0.3)
        handles, labels = [], []
    if handles:
        width = fig.get_size_inches()[0]
        fig.tight_layout(rect=(0, 0, 1 - label_w / width, 1))
        fig.legend(handles, labels, loc="center left", bbox_to_anchor=(1 - label_w / width + 0.005, 0.5),
                   fontsize=9, frameon=False, title="method", title_fontsize=9)
    else:
        fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _legend(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    fig, ax = plt.subplots(figsize=(4.8, 0.9), dpi=100)
    norm = LogNorm(*ERR_RANGE)
    fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap=_CMAP), cax=ax, orientation="horizontal",
                 label="per-pixel relMSE")
    fig.subplots_adjust(left=0.05, right=0.95, top=0.92, bottom=0.62)
    fig.savefig(path)
    plt.close(fig)


def _fmt(v: Any) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _means_table(summary: list[dict[str, Any]], subset: str, metrics: list[str]) -> str:
    rows = [s for s in summary if s["subset"] == subset]
    head = "".join(f"<th>{html.escape(m)}{' &darr;' if m in _LOWER_BETTER else ' &uarr;'}</th>" for m in metrics)
    out = [f"<table><tr><th>spp</th><th>method</th><th>images</th>{head}<th>ms / MP</th></tr>"]
    for s in sorted(rows, key=lambda s: s["spp"]):
        cells = "".join(f"<td>{_fmt(s.get(m))}</td>" for m in metrics)
        out.append(f"<tr><td>{s['spp']}</td><td>{html.escape(s['method'])}</td><td>{s['images']}</td>{cells}"
                   f"<td>{_fmt(s.get('ms_per_mpix'))}</td></tr>")
    out.append("</table>")
    return "\n".join(out)


_CSS = """
body { font-family: sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.85em; }
td, th { border: 1px solid #ccc; padding: 2px 6px; text-align: right; }
th { background: #f0f0f0; }
table.rank td.name { text-align: left; }
table.rank caption { text-align: left; font-weight: bold; padding: 2px 0; }
table.crops td, table.crops th { text-align: center; vertical-align: top; font-size: 0.9em; border: none; padding: 2px; }
table.crops th { background: none; white-space: nowrap; }
img.px { image-rendering: pixelated; display: block; margin-bottom: 2px; }
.meta { font-size: 0.85em; color: #555; }
"""


def _title(doc: dict[str, Any]) -> str:
    """What was evaluated, for the page title: the data folders' names, the split, images, spp."""
    names = [Path(d).name or str(d) for d in doc["config"]["data"]]
    data = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    spp = ", ".join(map(str, sorted({s["spp"] for s in doc["summary"]}) or doc["config"]["spp"]))
    datasets = any((Path(d) / "manifest.json").is_file() for d in doc["config"]["data"])
    split = f" ({doc['config']['split']} split)" if datasets else ""  # image folders have no split
    return f"{data}{split}: {len(doc['images'])} image(s) at {spp} spp"


def _crop_table(image: str, ent: dict[str, Any], relmse: dict[tuple[str, int, str], Any]) -> str:
    """One table per image: a row per spp, a column per method, so every row lines up."""
    e = html.escape
    y0, x0, h, w = ent["window"]
    scale = max(1, 160 // max(h, w))
    size = f"width='{w * scale}' height='{h * scale}'"
    names = list(dict.fromkeys(n for cells in ent["cells"].values() for n in cells))
    out = ["<table class='crops'><tr><th></th>" + "".join(f"<th>{e(n)}</th>" for n in names) + "<th>reference</th></tr>"]
    for spp, cells in sorted(ent["cells"].items()):
        tds = []
        for name in names:
            if name not in cells:
                tds.append("<td></td>")
                continue
            png, err = cells[name]
            tds.append(f"<td><img class='px' src='{e(png)}' {size} alt='{e(name)}'>"
                       f"<img class='px' src='{e(err)}' {size} alt='{e(name)} error'>"
                       f"{_fmt(relmse.get((image, spp, name)))}</td>")
        tds.append(f"<td><img class='px' src='{e(ent['ref'])}' {size} alt='reference'></td>")
        out.append(f"<tr><th>{spp} spp</th>" + "".join(tds) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def write_report(root: Path, doc: dict[str, Any], crops: CropWriter) -> Path:
    """``index.html``, the plot and the legend in ``root``; returns the page's path.

    The page leads with the ranked summary (:mod:`mcdenoise.eval.ranking`), then the plot, the
    table of every metric, and the crops."""
    from mcdenoise.eval.ranking import same_images, summary_html
    from mcdenoise.io.atomic import atomic_file

    root = Path(root)
    methods = [m["name"] for m in doc["methods"]]
    metrics = list(doc["config"]["metrics"])
    summary = doc["summary"]
    same = same_images(doc)
    _plot(root / "relmse_vs_spp.png", summary, methods, same)
    _legend(root / "error_legend.png")
    relmse = {(r["image"], r["spp"], r["method"]): r.get("relmse") for r in doc["rows"]}
    p = doc["provenance"]
    e = html.escape
    title = _title(doc)
    n_sub = max((s["images"] for s in summary if s["subset"] == "dof_motion"), default=0)
    if same:
        subset_note = f" All {n_sub} images have depth of field or motion blur."
    elif n_sub:
        subset_note = f" {n_sub} of them have depth of field or motion blur (own tables below)."
    else:
        subset_note = ""
    parts = [
        "<!DOCTYPE html>", "<html lang='en'><head><meta charset='utf-8'>",
        f"<title>{e(title)} - mcdenoise eval</title>", f"<style>{_CSS}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        f"<p class='meta'><code>{e(doc['command'])}</code><br>{e(p['date'])} &middot; {e(p['machine'])} &middot; "
        f"mcdenoise {e(p['mcdenoise'])} &middot; torch {e(p['torch'])}"
        + (f" &middot; OIDN {e(p['oidn'])}" if "oidn" in p else "") + f" &middot; device {e(p['device'])}</p>",
        f"<p>{len(doc['images'])} images, split <b>{e(doc['config']['split'])}</b>, spp "
        f"{', '.join(map(str, doc['config']['spp']))}.{e(subset_note)} Times: wall time of the denoise call only, after one "
        "warm-up call per method; ms per megapixel = total time / total megapixels.</p>",
        "<h2>Ranking</h2>",
        summary_html(doc, "all"),
    ]
    if n_sub and not same:
        parts += ["<h3>Depth-of-field / motion-blur images</h3>", summary_html(doc, "dof_motion", note=False)]
    if doc.get("seed_spread"):
        parts += ["<h3>Spread over render seeds</h3>", f"<pre>{e(spread_text(doc['seed_spread']))}</pre>"]
    if doc["notes"]:
        parts.append("<details><summary>notes</summary><ul>" + "".join(f"<li>{e(n)}</li>" for n in doc["notes"])
                     + "</ul></details>")
    parts.append("<h2>relMSE per method</h2><img src='relmse_vs_spp.png' alt='mean relMSE per method and spp'>")
    parts.append("<h2>Every metric, means over all images</h2>")
    parts.append(_means_table(summary, "all", metrics))
    if n_sub and not same:
        parts.append("<h2>Every metric, means over depth-of-field / motion-blur images</h2>")
        parts.append(_means_table(summary, "dof_motion", metrics))
    parts.append("<h2>Images</h2><p>Tonemapped crops (reinhard) and per-pixel relMSE below each; "
                 "the number is the whole image's relMSE.</p>"
                 "<img src='error_legend.png' alt='error map colour scale'>")
    info = {im["id"]: im for im in doc["images"]}
    for image, ent in crops.entries.items():
        im = info[image]
        y0, x0, h, w = ent["window"]
        fx = ", ".join(im["effects"]) or "no depth of field or motion blur"
        parts.append(f"<h3 id='{e(ent['dir'])}'>{e(image)}</h3><p class='meta'>{im['width']}x{im['height']}, "
                     f"{im['spp']} spp stored, reference {im['reference_spp']} spp; {e(fx)}; crop x {x0}..{x0 + w - 1}, "
                     f"y {y0}..{y0 + h - 1}</p>")
        parts.append(_crop_table(image, ent, relmse))
    parts.append("</body></html>")
    path = root / "index.html"
    with atomic_file(path) as tmp:
        tmp.write_text("\n".join(parts) + "\n")
    return path
