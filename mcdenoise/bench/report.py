"""Markdown tables of a ``mcdenoise bench`` result (the dict of :func:`mcdenoise.bench.run.run_bench`).

Ratios to OIDN divide by OIDN's median at the same size from the same rounds (OIDN is timed in
the group of the pixel models and of the sample models at 8 spp). The fraction of peak is the
model's convolution/matmul FLOPs (counted at 64x64, per output pixel) times the pixel count over
its time, divided by the GFLOP/s of one large 3x3 convolution measured in the same run.
"""

from __future__ import annotations

from typing import Any

from mcdenoise.bench.plan import TARGETS

__all__ = ["ratios", "target_rows", "api_rows", "markdown"]

#: The public API counts as agreeing with the bare model call within this fraction (issue 18).
API_TOLERANCE = 0.10


def _ok(res: dict[str, Any]) -> list[dict[str, Any]]:
    return [e for e in res["entries"] if e["status"] == "ok"]


def _needs_prefiltered_oidn(method: str) -> bool:
    """Whether a ``combine:PRESET`` entry's candidates include OIDN on prefiltered guides
    (``oidn:high-pf``): read from the preset's configuration, so every such preset counts."""
    name, _, preset = method.removesuffix(" api").partition(":")
    if name != "combine":
        return False
    from mcdenoise.models.registry import list_models

    entry = next((e for e in list_models() if e.name == name), None)
    return bool(entry and preset in entry.presets and getattr(entry.config(preset), "prefiltered", False))


def _oidn(res: dict[str, Any], w: int, h: int, quality: str) -> float | None:
    for e in _ok(res):
        if e["method"] == f"oidn:{quality}" and (e["width"], e["height"]) == (w, h):
            return e["median_s"]
    return None


def ratios(res: dict[str, Any], entry: dict[str, Any]) -> dict[str, float | None]:
    """``{"high": t / t_oidn_high, "fast": t / t_oidn_fast}`` at the entry's size (None if unmeasured)."""
    out: dict[str, float | None] = {}
    for q in ("high", "fast"):
        t = _oidn(res, entry["width"], entry["height"], q)
        out[q] = entry["median_s"] / t if t else None
    return out


def target_rows(res: dict[str, Any], size: tuple[int, int] = (1920, 1080)) -> list[dict[str, Any]]:
    """Issue 12's CPU targets against this run: method, spp, limit, ratio and met (both None when
    not measured: a target this run did not time is neither met nor missed)."""
    rows = []
    for label, spp, limit in TARGETS:
        hit = [e for e in _ok(res) if e["method"] == label and e["spp"] == spp and (e["width"], e["height"]) == size]
        if not hit and label not in res["config"]["methods"]:
            continue
        r = ratios(res, hit[0])["high"] if hit else None
        rows.append({"method": label, "spp": spp, "limit": limit, "ratio": r,
                     "median_s": hit[0]["median_s"] if hit else None, "met": None if r is None else r <= limit})
    return rows


def api_rows(res: dict[str, Any]) -> list[dict[str, Any]]:
    """Each ``NAME:PRESET api`` entry beside its bare model call at the same size and spp:
    both medians, their ratio, and whether the API is within :data:`API_TOLERANCE` of the call."""
    ok = _ok(res)
    bare = {(e["method"], e["width"], e["height"], e["spp"]): e for e in ok}
    rows = []
    for e in ok:
        if not e["method"].endswith(" api"):
            continue
        b = bare.get((e["method"][: -len(" api")], e["width"], e["height"], e["spp"]))
        if b is None:
            continue
        r = e["median_s"] / b["median_s"]
        rows.append({"method": b["method"], "width": e["width"], "height": e["height"], "spp": e["spp"],
                     "model_s": b["median_s"], "api_s": e["median_s"], "ratio": r, "within": r <= 1 + API_TOLERANCE})
    return rows


def _fmt(x: float | None, spec: str, none: str = "-") -> str:
    return none if x is None else format(x, spec)


def _busy(machine: dict[str, Any], key: str, when: str) -> str | None:
    """The overload warning of a recorded load average against the recorded core count."""
    load, cores = machine.get(key), machine.get("cores")
    if load is None or not cores or load <= cores:
        return None
    return f"load average {load:g} {when} exceeded the {cores} cores: other work shared the CPU, times are slower and noisier"


def _met(met: bool | None) -> str:
    return "not measured" if met is None else "yes" if met else "**no**"


def _ms(s: float) -> str:
    return f"{s * 1e3:,.0f}" if s >= 1 else f"{s * 1e3:.1f}"


def markdown(res: dict[str, Any], command: str = "") -> str:
    """The whole report: machine, timing tables per size, spp scaling, training, targets, skips."""
    m = res["machine"]
    pk = res["peak_conv"]
    lines = [
        f"Measured {m['date']} on {m['cpu']}, {m['cores']} cores, {m.get('memory_gib', '?')} GiB, "
        f"torch {m['torch']} ({m['torch_threads']} threads), OIDN {m['oidn']}"
        + (f" ({m['oidn_threads']} threads)" if m.get("oidn_threads") else "") + f", device {m['device']}"
        + (f" ({m['gpu']})" if m.get("gpu") else "") + f"; load average {m.get('load_start')} at start, "
        f"{m.get('load_end')} at end; {res['wall_s']:.0f} s wall.",
        "",
    ]
    busy = [w for w in (_busy(m, "load_start", "at start"), _busy(m, "load_end", "at end")) if w]
    if busy:
        lines += [f"**Warning**: {'; '.join(busy)}.", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    c = res["config"]
    slow = f" (one round for calls over {c['slow_s']:g} s after the first size)" if c.get("slow_s") else ""
    lines += [
        f"Median of {c['rounds']} interleaved rounds after {c['warmup']} warm-up call(s)"
        f"{slow}; fast inference paths "
        f"{'on' if c['fast'] else 'off'}, convolution trunks in {c.get('precision', 'float32')}. Peak memory: {res['memory_method']}. Machine peak: a 3x3 convolution, "
        f"{pk['channels']} channels at {pk['side']}x{pk['side']}{' in ' + pk['precision'] if pk.get('precision') else ''}, "
        f"ran at **{pk['gflops']:.1f} GFLOP/s**.",
        "",
    ]
    sizes = [tuple(s) for s in c["sizes"]]
    for w, h in sizes:
        rows = [e for e in _ok(res) if (e["width"], e["height"]) == (w, h)]
        if not rows:
            continue
        lines += [f"### {w}x{h}", "",
                  "| method | spp | median ms | x OIDN high | x OIDN fast | peak MiB above inputs | MFLOP/pixel | % of peak |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for e in sorted(rows, key=lambda e: (not e["method"].startswith("oidn"), e["method"], e["spp"] or 0)):
            r = ratios(res, e)
            fpp = e.get("flops_per_pixel")
            frac = fpp * w * h / e["median_s"] / (pk["gflops"] * 1e9) * 100 if fpp else None
            peak = e.get("peak_bytes")
            lines.append(
                f"| {e['method']} | {e['spp'] if e['spp'] is not None else '-'} | {_ms(e['median_s'])} | "
                f"{_fmt(r['high'], '.3g')} | {_fmt(r['fast'], '.3g')} | {_fmt(peak / 2**20 if peak is not None else None, ',.0f')} | "
                f"{_fmt(fpp / 1e6 if fpp else None, '.3g')} | {_fmt(frac, '.1f')} |")
        comb = [e for e in rows if e["method"].startswith("combine:")]
        hi = _oidn(res, w, h, "high")
        if comb and hi:
            paths = []
            for e in comb:
                # the OIDN runs the combiner's candidates need: high, and prefiltered high for `ens`
                # (its API row too: the API is given the candidates like the bare call)
                need = ["high"] + (["high-pf"] if _needs_prefiltered_oidn(e["method"]) else [])
                pre = [_oidn(res, w, h, q) for q in need]
                if None in pre:
                    paths.append(f"{e['method']} not measured (needs oidn:{' and oidn:'.join(need)})")
                    continue
                t = e["median_s"] + sum(pre)
                paths.append(f"{e['method']} {_ms(t)} ({t / hi:.3g}x OIDN high; with oidn:{' + oidn:'.join(need)})")
            lines += ["A combiner's time above is its own (OIDN's outputs are its inputs); with the OIDN runs it "
                      "needs first, the whole path takes " + ", ".join(paths) + ".", ""]
        lines.append("")
    lines += _api(res)
    lines += _scaling(res, sizes)
    lines += _training(res)
    tr = target_rows(res)
    if tr:
        lines += ["### Targets (CPU, ratio to OIDN high at 1920x1080, same run)", "",
                  "| method | spp | limit | measured | median ms | met |", "|---|---:|---:|---:|---:|---|"]
        for t in tr:
            lines.append(f"| {t['method']} | {t['spp'] or '-'} | <= {t['limit']:g}x | {_fmt(t['ratio'], '.3g', 'not measured')} | "
                         f"{_ms(t['median_s']) if t['median_s'] else '-'} | {_met(t['met'])} |")
        lines.append("")
    other = [e for e in res["entries"] if e["status"] != "ok"]
    if other:
        lines += ["Not measured:", ""]
        lines += [f"- {e['method']} {e['width']}x{e['height']}" + (f" {e['spp']} spp" if e["spp"] else "")
                  + f": {e['status']}, {e['reason']}" for e in other]
        lines.append("")
    return "\n".join(lines)


def _api(res: dict[str, Any]) -> list[str]:
    rows = api_rows(res)
    if not rows:
        return []
    out = ["### Public API against the bare model call (same rounds)", "",
           "`NAME:PRESET api` is `mcdenoise.denoise(color, albedo=, normal=, depth=, features=, samples=, "
           "model=<shipped weights>)` on numpy arrays, repeated calls; the bare call is the model's forward on "
           f"tensors already in place. The API agrees when it takes at most {1 + API_TOLERANCE:g}x the bare call.", "",
           "| method | size | spp | model ms | API ms | API / model | agrees |", "|---|---|---:|---:|---:|---:|---|"]
    for r in rows:
        out.append(f"| {r['method']} | {r['width']}x{r['height']} | {r['spp'] if r['spp'] is not None else '-'} | "
                   f"{_ms(r['model_s'])} | {_ms(r['api_s'])} | {r['ratio']:.2f} | {'yes' if r['within'] else '**no**'} |")
    return out + [""]


def _scaling(res: dict[str, Any], sizes: list[tuple[int, int]]) -> list[str]:
    spps = sorted(res["config"]["spp"])
    if len(spps) < 2:
        return []
    out = ["### Time against spp (time / time at the lowest spp measured)", "",
           "| method | size | " + " | ".join(f"{s} spp" for s in spps) + " |",
           "|---|---|" + "---:|" * len(spps)]
    found = False
    for w, h in sizes:
        per: dict[str, dict[int, float]] = {}
        for e in _ok(res):
            if (e["width"], e["height"]) == (w, h) and e["spp"] is not None:
                per.setdefault(e["method"], {})[e["spp"]] = e["median_s"]
        for method, ts in sorted(per.items()):
            if len(ts) < 2:
                continue
            base = ts[min(ts)]
            out.append(f"| {method} | {w}x{h} | " + " | ".join(_fmt(ts[s] / base if s in ts else None, '.2f') for s in spps) + " |")
            found = True
    return out + [""] if found else []


def _training(res: dict[str, Any]) -> list[str]:
    if not res["training"]:
        return []
    t = res["config"]["train"]
    out = [f"### Training throughput (batch {t['batch']}, {t['crop']}x{t['crop']} crops, {t['spp']} spp for sample "
           "models; forward, loss, backward, clipped Adam step on crops in memory)", "",
           "| method | parameters (inference form) | s/step | crops/s |", "|---|---:|---:|---:|"]
    for r in res["training"]:
        p = res["parameters"].get(r["method"])
        if "error" in r:
            out.append(f"| {r['method']} | {_fmt(p, ',d')} | error: {r['error']} | - |")
        else:
            out.append(f"| {r['method']} | {_fmt(p, ',d')} | {r['s_per_step']:.3f} | {r['crops_per_s']:.1f} |")
    return out + [""]
