"""Where does a model win or lose against another: per kind of lighting of our procedural images.
Per image of an eval report, NEW's relMSE divided by OLD's, grouped by what the generator put in
the scene (its ``meta.json``): small bright emitters (the rich world's bulbs) or none, and with
``--detail`` also indoor with a window, indoor with lamps, or outdoor. Prints per spp and group
the number of images and the geometric-mean ratio. With ``--metric psnr`` it prints instead the mean
PSNR difference NEW - OLD in dB and on how many images NEW is worse. Images without procedural
metadata (renders of scene files) form one group, ``scene file``. With ``--by-noise`` the groups
are instead the quartiles of the noisy input's relMSE at each spp (q1 the least noisy), over the
report's images, procedural or not.

Campaign 26 asked it of OIDN against layer-medium: on our held-out images with small bright
emitters layer-medium wins, on those without it loses, as on the third-party scenes.

    python scripts/ratio_by_lighting.py reports/c24_heldout/results.json oidn-high layer-medium --spp 4 8 16
    python scripts/ratio_by_lighting.py reports/c29_heldout/results.json layer-medium refine_c29 --metric psnr --all

Campaign 34 asked it by noise: on our held-out images layer-medium is 1.2x OIDN high's relMSE at
4 spp on the least noisy quartile and 0.55-0.67x on the others, and the third-party renderings are
mostly that kind of image.

    python scripts/ratio_by_lighting.py reports/c32_heldout_bands/results.json oidn-high layer-medium --by-noise --all
"""
from __future__ import annotations

import argparse
import collections
import json
import math
from pathlib import Path


def lighting_group(meta: dict, detail: bool = False) -> str:
    """The group of one image from its ``meta.json`` document: ``bulbs`` / ``no bulbs`` (the rich
    world's small emitters; the classic world has none), prefixed with ``window``, ``lamps`` or
    ``outdoor`` when ``detail``; ``scene file`` when the image is not procedural."""
    proc = (meta.get("extra") or {}).get("procedural")
    if not isinstance(proc, dict):
        return "scene file"
    rich = proc.get("rich") or {}
    group = "bulbs" if rich.get("small_emitters", 0) > 0 else "no bulbs"
    if not detail:
        return group
    where = "outdoor" if proc.get("kind") == "outdoor" else ("window" if rich.get("window") else "lamps")
    return f"{where}, {group}"


def noise_quartiles(noisy: dict[str, float]) -> tuple[dict[str, str], list[float]]:
    """image -> the noisy input's relMSE -> (image -> ``noise q1``..``noise q4`` by rank, q1 the least
    noisy, sizes as equal as the count allows; the five edges: least, the three boundaries' first
    values of the next quartile, most)."""
    order = sorted(noisy, key=lambda i: (noisy[i], i))
    n = len(order)
    q = [min(3, r * 4 // n) for r in range(n)]
    group = {im: f"noise q{q[r] + 1}" for r, im in enumerate(order)}
    starts = [r for r in range(1, n) if q[r] != q[r - 1]]
    edges = [noisy[order[0]], *(noisy[order[r]] for r in starts), noisy[order[-1]]]
    return group, edges


def geo_ratios(pairs: dict[str, list[tuple[float, float]]]) -> dict[str, tuple[int, float]]:
    """group -> [(new, old) relMSE per image] -> group -> (images, geometric mean of new / old)."""
    return {g: (len(v), math.exp(sum(math.log(n / o) for n, o in v) / len(v))) for g, v in pairs.items() if v}


def psnr_differences(pairs: dict[str, list[tuple[float, float]]]) -> dict[str, tuple[int, float, int]]:
    """group -> [(new, old) PSNR per image] -> group -> (images, mean of new - old in dB, images where
    new is lower)."""
    return {g: (len(v), sum(n - o for n, o in v) / len(v), sum(n < o for n, o in v)) for g, v in pairs.items() if v}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="results.json of `mcdenoise eval`")
    ap.add_argument("old", help="the method every ratio is taken against")
    ap.add_argument("new", nargs="+", help="methods whose relMSE is divided by OLD's")
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--detail", action="store_true", help="also split by window, lamps and outdoor")
    ap.add_argument("--all", action="store_true", help="also one column over every image of the report")
    ap.add_argument("--by-noise", action="store_true",
                    help="group by quartile of the noisy input's relMSE at each spp instead of by lighting")
    ap.add_argument("--metric", choices=("relmse", "psnr"), default="relmse",
                    help="relmse: geometric-mean ratio NEW / OLD; psnr: mean difference NEW - OLD (dB)")
    a = ap.parse_args()
    doc = json.loads(a.report.read_text())
    rel: dict[tuple[str, int], dict[str, float]] = collections.defaultdict(dict)
    noisy: dict[int, dict[str, float]] = collections.defaultdict(dict)
    for r in doc["rows"]:
        rel[(r["image"], r["spp"])][r["method"]] = r[a.metric]
        if r["method"] == "noisy":
            noisy[r["spp"]][r["image"]] = r["relmse"]
    for m in (a.old, *a.new):
        if not any(m in v for v in rel.values()):
            ap.error(f"{a.report}: no rows for {m}")
    by_spp: dict[int, dict[str, str]] = {}
    edges: dict[int, list[float]] = {}
    if a.by_noise:
        for spp in a.spp:
            if not noisy.get(spp):
                ap.error(f"{a.report}: no noisy rows at {spp} spp (--by-noise needs them)")
            by_spp[spp], edges[spp] = noise_quartiles(noisy[spp])
    else:
        lit = {im["id"]: lighting_group(json.loads((Path(im["path"]) / "meta.json").read_text()), a.detail)
               for im in doc["images"]}
        by_spp = {spp: lit for spp in a.spp}
    groups = sorted({g for v in by_spp.values() for g in v.values()}) + (["all images"] if a.all else [])
    what = "geometric-mean relMSE ratio to" if a.metric == "relmse" else "mean PSNR difference (dB) from"
    print(f"{what} {a.old}")
    print(f"{'spp':>3}  {'method':<20} " + "  ".join(f"{g:>26}" for g in groups))
    for spp in a.spp:
        group = by_spp[spp]
        for m in a.new:
            pairs: dict[str, list[tuple[float, float]]] = collections.defaultdict(list)
            for (i, s), v in rel.items():
                if s == spp and m in v and a.old in v:
                    pairs[group[i]].append((v[m], v[a.old]))
                    if a.all:
                        pairs["all images"].append((v[m], v[a.old]))
            if a.metric == "relmse":
                res = geo_ratios(pairs)
                cells = [f"{res[g][1]:.4f} (n={res[g][0]})" if g in res else "-" for g in groups]
            else:
                dif = psnr_differences(pairs)
                cells = [f"{dif[g][1]:+.5f} dB ({dif[g][2]}/{dif[g][0]} lower)" if g in dif else "-" for g in groups]
            print(f"{spp:>3}  {m[:20]:<20} " + "  ".join(f"{c:>26}" for c in cells))
    for spp, e in edges.items():
        print(f"noisy relMSE at {spp} spp, quartile edges: " + " / ".join(f"{v:.4g}" for v in e))


if __name__ == "__main__":
    main()
