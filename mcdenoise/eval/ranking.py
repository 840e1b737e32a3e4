"""The ranked summary that leads ``mcdenoise eval``'s page and its terminal output.

Per spp, every method with its mean relMSE, PSNR, SSIM, FLIP (when computed), time per
megapixel and relMSE ratio to OIDN ``high`` (below 1 beats OIDN), best relMSE first; the best
value of each column is marked (bold on the page, ``*`` in the terminal). The noisy input is
ranked too: it is the floor every denoiser must beat.
"""

from __future__ import annotations

import html
from typing import Any

from mcdenoise.eval.seeds import spread_text

__all__ = ["COLUMNS", "ranked", "timing_note", "summary_text", "summary_html", "same_images"]

#: (key, header, better: "min" or "max", format) of the ranked table, in order.
COLUMNS: tuple[tuple[str, str, str, str], ...] = (
    ("relmse", "relMSE", "min", ".4g"),
    ("psnr", "PSNR dB", "max", ".2f"),
    ("ssim", "SSIM", "max", ".4f"),
    ("flip", "FLIP", "min", ".4f"),
    ("ms_per_mpix", "ms/MP", "min", "ms"),
    ("vs_oidn", "x OIDN high", "min", ".3g"),
)
OIDN_REF = "oidn-high"


def same_images(doc: dict[str, Any]) -> bool:
    """True when the depth-of-field / motion-blur subset holds every image (its tables would
    repeat the main ones)."""
    n_all = {s["spp"]: s["images"] for s in doc["summary"] if s["subset"] == "all"}
    n_sub = {s["spp"]: s["images"] for s in doc["summary"] if s["subset"] == "dof_motion"}
    return bool(n_sub) and n_sub == n_all


def ranked(doc: dict[str, Any], subset: str = "all") -> list[dict[str, Any]]:
    """Per spp: ``{"spp", "images", "columns": [(key, header, better, fmt)], "rows": [{"method",
    key: value, "best": set of keys}]}``, rows by relMSE (methods without one last)."""
    summary = [s for s in doc["summary"] if s["subset"] == subset]
    metrics = set(doc["config"]["metrics"])
    out = []
    for k in doc["config"]["spp"]:
        rows = [dict(s) for s in summary if s["spp"] == k]
        if not rows:
            continue
        ref = next((r.get("relmse") for r in rows if r["method"] == OIDN_REF), None)
        for r in rows:
            r["vs_oidn"] = r["relmse"] / ref if ref and r.get("relmse") is not None else None
        cols = [c for c in COLUMNS
                if (c[0] in metrics or c[0] in ("ms_per_mpix", "vs_oidn"))
                and any(r.get(c[0]) is not None for r in rows)]
        rows.sort(key=lambda r: (r.get("relmse") is None, r.get("relmse") or 0.0))
        for r in rows:
            r["best"] = set()
        for key, _, better, _ in cols:
            vals = [r[key] for r in rows if r.get(key) is not None]
            if len(vals) < 2:
                continue  # nothing to compare against
            best = min(vals) if better == "min" else max(vals)
            for r in rows:
                if r.get(key) == best:
                    r["best"].add(key)
        out.append({"spp": k, "images": max(r["images"] for r in rows), "columns": cols, "rows": rows})
    return out


def timing_note(doc: dict[str, Any]) -> str:
    """One line saying what the ms/MP column measured: device, CPU, thread counts, precision."""
    cfg, p = doc["config"], doc["provenance"]
    precisions = sorted({m.get("precision", "float32") for m in doc["methods"] if m.get("kind") == "model"})
    oidn = cfg.get("oidn_threads")
    threads = f"torch {cfg.get('threads', p.get('torch_threads'))} thread(s)"
    if cfg.get("oidn"):
        threads += f", OIDN {oidn} thread(s)" if oidn is not None else ", OIDN every core"
    prec = f"; models in {' and '.join(precisions)}" if precisions else ""
    busy = [n.removeprefix("timing: ") for n in doc["notes"] if n.startswith("timing: ")]
    warn = f" Warning: {'; '.join(busy)}." if busy else ""
    return (f"ms/MP: wall time of the denoise call per megapixel on {p.get('device', '?')} "
            f"({p.get('cpu', p.get('machine', '?'))}), {threads}{prec}; x OIDN high: relMSE / OIDN high's "
            f"relMSE (below 1 beats it).{warn}")


def _fmt(v: Any, spec: str) -> str:
    if v is None:
        return "-"
    if spec == "ms":  # whole milliseconds once they are large, 3 digits below
        return f"{v:,.0f}" if v >= 100 else f"{v:.3g}"
    return format(v, spec)


def summary_text(doc: dict[str, Any], subset: str = "all") -> str:
    """The ranked tables as plain text (``*`` marks the best of each column)."""
    lines = []
    for t in ranked(doc, subset):
        cols = t["columns"]
        width = max(len("method"), *(len(r["method"]) for r in t["rows"]))
        lines.append(f"{t['spp']} spp, mean over {t['images']} image(s), best relMSE first (* best in column):")
        lines.append(f"  {'#':>2}  {'method':<{width}}" + "".join(f"  {h:>11}" for _, h, _, _ in cols))
        for i, r in enumerate(t["rows"], 1):
            cells = "".join(f"  {_fmt(r.get(key), fmt) + ('*' if key in r['best'] else ' '):>11}"
                            for key, _, _, fmt in cols)
            lines.append(f"  {i:>2}  {r['method']:<{width}}{cells}")
        lines.append("")
    lines.append(timing_note(doc))
    return "\n".join(lines)


def terminal_summary(doc: dict[str, Any]) -> str:
    """What ``mcdenoise eval`` and ``mcdenoise demo`` print: :func:`summary_text`, then the same
    tables for the depth-of-field / motion-blur images alone when those are not all the images."""
    text = summary_text(doc)
    if any(s["subset"] == "dof_motion" for s in doc["summary"]) and not same_images(doc):
        text += "\n\nDepth-of-field / motion-blur images only:\n" + summary_text(doc, "dof_motion").rsplit("\n", 1)[0]
    if doc.get("seed_spread"):
        text += "\n\n" + spread_text(doc["seed_spread"])
    return text


def summary_html(doc: dict[str, Any], subset: str = "all", note: bool = True) -> str:
    """The ranked tables as HTML (best of each column in bold), one per spp; ``note``: the
    :func:`timing_note` under them."""
    e = html.escape
    out = []
    for t in ranked(doc, subset):
        cols = t["columns"]
        arrows = {"min": " &darr;", "max": " &uarr;"}
        head = "".join(f"<th>{e(h)}{arrows[b]}</th>" for _, h, b, _ in cols)
        out.append(f"<table class='rank'><caption>{t['spp']} spp, mean over {t['images']} image(s)</caption>"
                   f"<tr><th>#</th><th>method</th>{head}</tr>")
        for i, r in enumerate(t["rows"], 1):
            cells = "".join(
                f"<td>{'<b>' if key in r['best'] else ''}{_fmt(r.get(key), fmt)}{'</b>' if key in r['best'] else ''}</td>"
                for key, _, _, fmt in cols)
            out.append(f"<tr><td>{i}</td><td class='name'>{e(r['method'])}</td>{cells}</tr>")
        out.append("</table>")
    if note:
        out.append(f"<p class='meta'>{e(timing_note(doc))}</p>")
    return "\n".join(out)
