"""The reproductions' outputs besides the JSON: the validation-curve plot and the Markdown block
that ``--write-docs`` puts into ``docs/RESULTS.md`` (key ``repro:NAME``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mcdenoise.io.atomic import atomic_file

__all__ = ["METRIC_NAMES", "plot_curves", "markdown_block", "command_line", "spread"]

#: Validation metrics of the training engine (``val_<name>`` columns of metrics.csv), as printed.
METRIC_NAMES = {"relmse": "relMSE", "smape": "SMAPE", "l1": "L1", "psnr": "PSNR (dB)"}


def plot_curves(result: dict[str, Any], out_png: Path) -> Path:
    """Validation metric against steps, one line per variant (log y except PSNR)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = result["metric"]
    fig, ax = plt.subplots(figsize=(7, 4), dpi=100)
    for key, v in result["variants"].items():
        ax.plot([p["step"] for p in v["curve"]], [p[m] for p in v["curve"]], "o-", ms=3,
                label=f"{v['label']} ({v['parameters']:,} params)")
    if m != "psnr":
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel(f"validation {METRIC_NAMES[m]}")
    d = result["data"]
    ax.set_title(f"{result['title']}\n{d['val_images']} held-out images, batch {result['batch']} x {result['crop']}px, "
                 f"seed {result['seed']}", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out_png) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out_png


def command_line(result: dict[str, Any]) -> str:
    """The command that reproduces ``result`` (defaults left out)."""
    parts = ["mcdenoise", "repro", result["experiment"]]
    if not result["default_data"]:
        parts += ["--data", result["data"]["path"]]
    if result["steps"] != result["default_steps"]:
        parts += ["--steps", str(result["steps"])]
    if result["seed"]:
        parts += ["--seed", str(result["seed"])]
    return " ".join(parts)


def spread(curve: list[dict[str, float]], metric: str, last: int = 3) -> float:
    """max - min of ``metric`` over the last ``last`` validation points: how much a run still
    wobbles, a floor under which a difference between variants says little."""
    vals = [p[metric] for p in curve[-last:]]
    return max(vals) - min(vals)


def _fmt(metric: str, v: float) -> str:
    return f"{v:.2f}" if metric == "psnr" else f"{v:.4g}"


def _device(result: dict[str, Any]) -> str:
    devices = sorted({v["device"] for v in result["variants"].values()})
    if devices == ["cpu"]:
        return "the CPU (the project's machine has 2 cores, shared with other jobs while this ran)"
    return ", ".join(f"`{d}`" for d in devices)


def _data_line(result: dict[str, Any]) -> str:
    d = result["data"]
    src = "the procedural cache the command renders (`CACHE_DATASET` in mcdenoise/repro/common.py)" \
        if result["default_data"] else f"`{d['path']}`"
    target = (f"{d['reference_spp']}-spp references" if d["val_references"]
              else "no references: the validation target is the mean of held-out samples of each image")
    return (f"{src}: {d['train_images']} training images, {d['val_images']} validation image(s) of "
            f"{d['val_scenes']} held-out scene(s), {d['width']}x{d['height']} at {d['spp']} spp, {target}")


def markdown_block(result: dict[str, Any], notes: str = "") -> str:
    """The ``repro:NAME`` block: claim, command, table, curve, verdict and caveats."""
    m = result["metric"]
    mn = METRIC_NAMES[m]
    variants = result["variants"]
    steps_axis = [p["step"] for p in next(iter(variants.values()))["curve"]]
    lines = [f"### {result['title']}", "", f"**Paper:** {result['claim']}", "",
             f"**Command:** `{command_line(result)}` ({result['steps']} steps per variant, batch {result['batch']} "
             f"crops of {result['crop']}x{result['crop']}, seed {result['seed']}; every variant on the same data, "
             f"steps, batch and crops; training took {result['wall_s_training'] / 60:.1f} min in all on {_device(result)}).", "",
             f"**Data:** {_data_line(result)}.", "",
             "**Final validation metrics** (whole held-out images, after the last step):", "",
             f"| variant | model | parameters | relMSE | SMAPE | L1 | PSNR (dB) | {mn} spread, last 3 validations | paper |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|"]
    for key, v in variants.items():
        f = v["final"]
        paper = ", ".join(f"{METRIC_NAMES.get(k, k)} {x:g}" for k, x in result["paper"].get(key, {}).items()) or "-"
        over = ", ".join(f"{k}={x}" for k, x in v["overrides"].items())
        model = f"`{v['model']}` small" + (f" ({over})" if over else "")
        lines.append(f"| {v['label']} | {model} | {v['parameters']:,} | {f['relmse']:.4g} | {f['smape']:.4g} | "
                     f"{f['l1']:.4g} | {f['psnr']:.2f} | {_fmt(m, spread(v['curve'], m))} | {paper} |")
    lines += ["", f"**Validation {mn} against steps:**", "",
              "| variant | " + " | ".join(str(s) for s in steps_axis) + " |",
              "|---|" + "---:|" * len(steps_axis)]
    for v in variants.values():
        lines.append(f"| {v['label']} | " + " | ".join(_fmt(m, p[m]) for p in v["curve"]) + " |")
    lines += ["", f"**Verdict: {result['verdict']}.** {result['explanation']}", "",
              f"**Caveats of scale:** one seed, {result['steps']} steps of batch {result['batch']} (the papers train "
              f"for days on thousands of 128-256 px images), the `small` presets (tens of thousands of parameters, "
              f"not millions), {result['data']['train_images']} training images, references with their own noise (the "
              f"same floor under every variant); a difference smaller than the spread column, or of a few percent, "
              f"is within what another seed or a longer run could reverse. "
              f"`--steps N` trains longer (runs resume; a new N starts new runs).{(' ' + notes) if notes else ''}",
              "", f"Curves: `{result['plot']}`; every figure: `{result['json']}`."]
    return "\n".join(lines)
