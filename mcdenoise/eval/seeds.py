"""How much of an evaluation's mean is the luck of one rendering (issue 19, campaign 23).

``mcdenoise eval --scenes DIR --render-seed 7 8 9 ...`` renders each scene's inputs once per
sampler seed. Every (scene, seed) pair is one image of the report, so the ranked tables are means
over scenes and seeds alike. This module adds what one seed cannot show: each method's mean over
the scenes of each seed, and how far those per-seed means spread. Why it matters: on the nine
third-party scenes the shipped layer-medium's 4-spp mean relMSE ran from 0.111 to 0.181 over six
seeds, and its ratio to OIDN 2.5.1 high from 1.18 to 1.66; seed 7, the one every earlier figure
used, was its most favourable (docs/TRAINING.md, campaign 23).
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import numpy as np

__all__ = ["seed_spread", "spread_rows", "spread_text", "spread_markdown"]


def seed_spread(rows: list[dict[str, Any]], images: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (method, spp): the mean relMSE and PSNR over the images of each render seed.

    ``rows``: the report's rows (``image``, ``method``, ``spp``, ``relmse``, ``psnr``); ``images``:
    its ``images`` entries (``id``, ``scene``, ``seed``). Empty unless there are two or more seeds
    and every seed holds the same scenes (otherwise the per-seed means would compare other scenes,
    not other luck). A method and spp with a missing or non-finite value on some seed is left out.
    """
    seed_of = {im["id"]: im.get("seed") for im in images}
    scenes: dict[Any, set[str]] = defaultdict(set)
    for im in images:
        scenes[im.get("seed")].add(im["scene"])
    seeds = sorted(s for s in scenes if s is not None)
    if len(seeds) < 2 or None in scenes or any(scenes[s] != scenes[seeds[0]] for s in seeds):
        return []
    groups: dict[tuple[str, int], dict[int, list[tuple[float, float]]]] = defaultdict(lambda: defaultdict(list))
    order: list[tuple[str, int]] = []
    for r in rows:
        key = (r["method"], r["spp"])
        if key not in groups:
            order.append(key)
        groups[key][seed_of[r["image"]]].append((r["relmse"], r["psnr"]))
    out = []
    for method, spp in order:
        per = groups[(method, spp)]
        vals = [per.get(s, []) for s in seeds]
        flat = [v for seed_vals in vals for pair in seed_vals for v in pair]
        if any(not seed_vals for seed_vals in vals) or any(v is None or not np.isfinite(v) for v in flat):
            continue
        out.append({"method": method, "spp": spp, "seeds": seeds, "images_per_seed": len(vals[0]),
                    "relmse": [float(np.mean([a for a, _ in v])) for v in vals],
                    "psnr": [float(np.mean([b for _, b in v])) for v in vals]})
    return out


def spread_rows(spread: list[dict[str, Any]], baseline: str = "oidn-high") -> list[dict[str, Any]]:
    """Per entry of :func:`seed_spread`: the mean, sample standard deviation and range over the seeds
    of the per-seed relMSE means, the same for PSNR, and (where ``baseline`` was run at that spp,
    for every other method) the range of the per-seed ratio of relMSE to the baseline's and the
    ratio of the two means over seeds."""
    base = {s["spp"]: np.array(s["relmse"]) for s in spread if s["method"] == baseline}
    out = []
    for s in spread:
        r, p = np.array(s["relmse"]), np.array(s["psnr"])
        row = {"method": s["method"], "spp": s["spp"], "relmse": r.mean(), "relmse_sd": r.std(ddof=1),
               "relmse_min": r.min(), "relmse_max": r.max(), "psnr": p.mean(), "psnr_sd": p.std(ddof=1)}
        if s["method"] != baseline and s["spp"] in base:
            q = r / base[s["spp"]]
            row.update(ratio_min=q.min(), ratio_max=q.max(), ratio_of_means=r.mean() / base[s["spp"]].mean())
        out.append(row)
    return out


def _intro(spread: list[dict[str, Any]]) -> str:
    seeds = spread[0]["seeds"]
    return (f"Spread over the {len(seeds)} render seeds ({', '.join(map(str, seeds))}): the mean over each seed's "
            f"{spread[0]['images_per_seed']} image(s), then mean +- standard deviation [range] of those means")


def spread_text(spread: list[dict[str, Any]], baseline: str = "oidn-high") -> str:
    """:func:`spread_rows` as plain text, one line per method and spp; empty for an empty spread."""
    if not spread:
        return ""
    width = max(len(s["method"]) for s in spread)
    lines = [_intro(spread) + ":"]
    for r in spread_rows(spread, baseline):
        line = (f"  {r['spp']:>3} spp  {r['method']:<{width}}  relMSE {r['relmse']:.4f} +- {r['relmse_sd']:.4f} "
                f"[{r['relmse_min']:.4f}-{r['relmse_max']:.4f}]  PSNR {r['psnr']:.2f} +- {r['psnr_sd']:.2f}")
        if "ratio_min" in r:
            line += f"  x {baseline} {r['ratio_min']:.2f}-{r['ratio_max']:.2f} (of the means: {r['ratio_of_means']:.2f})"
        lines.append(line)
    return "\n".join(lines)


def spread_markdown(spread: list[dict[str, Any]], baseline: str = "oidn-high") -> list[str]:
    """:func:`spread_rows` as Markdown lines (an intro and a table); empty for an empty spread."""
    if not spread:
        return []
    lines = [_intro(spread) + f"; the last columns divide each seed's relMSE by {baseline}'s on the same seed.", "",
             f"| spp | method | relMSE | range | PSNR | x {baseline}, per seed | x {baseline}, of the means |",
             "|---|---|---|---|---|---|---|"]
    for r in spread_rows(spread, baseline):
        ratio = (f"{r['ratio_min']:.2f}-{r['ratio_max']:.2f} | {r['ratio_of_means']:.2f}" if "ratio_min" in r else "- | -")
        lines.append(f"| {r['spp']} | {r['method']} | {r['relmse']:.4g} +- {r['relmse_sd']:.2g} | "
                     f"{r['relmse_min']:.4g}-{r['relmse_max']:.4g} | {r['psnr']:.2f} +- {r['psnr_sd']:.2f} | {ratio} |")
    return lines
