"""Evidence for the next campaign (issue 19): third-party validation relMSE of every shipped model
against the training CPU-hours and training megapixels that made it, one point per version of its
model card in git history (every version that carries a third-party validation block).

Cumulative figures follow each card's chain of fine-tunes (``training.init``): CPU-seconds as the
cards record them (loader workers included), GPU-seconds for runs on a lent GPU (``training.gpu_s``;
such versions are left off the CPU-hours plot), *dataset* megapixels (images x views x pixels of
every dataset in the chain) and *seen* megapixels (steps x batch x crop^2 of every training run).

    python scripts/training_evidence.py --out docs/img/training_evidence.png --spp 8
"""
from __future__ import annotations

import argparse
import json
import re
import shlex
import subprocess
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = "mcdenoise/models/shipped"
#: `mcdenoise train` defaults the commands may leave out.
DEFAULTS = {"--batch": 8, "--crop": 48, "--steps": 2000}


def _flag(cmd: str, name: str, default: float | None = None) -> float | None:
    args = shlex.split(cmd)
    for i, a in enumerate(args[:-1]):
        if a == name:
            return float(args[i + 1])
    return default


def dataset_mp(cmd: str | None) -> float:
    """Megapixels of the images a `mcdenoise dataset` command renders (all splits); a card of a
    run on several datasets joins their commands with ` && `."""
    if not cmd:
        return 0.0
    if " && " in cmd:
        return sum(dataset_mp(c) for c in cmd.split(" && "))
    size = _flag(cmd, "--size", 64.0)
    w, h = _flag(cmd, "--width", size), _flag(cmd, "--height", size)
    return (_flag(cmd, "--count", 0.0) or 0.0) * (_flag(cmd, "--views", 1.0) or 1.0) * w * h / 1e6


def chain_dataset_mp(st: list[dict[str, Any]]) -> float:
    """Megapixels of every dataset of a chain, each once however many stages trained on it (a
    dataset is its ``--out`` and ``--seed``: older cards spell the same command differently)."""
    import re

    unique: dict[tuple[str, str], str] = {}
    recorded = 0.0
    for s in st:
        if s.get("images_mp") is not None:
            recorded += float(s["images_mp"])
            continue
        for c in (s["dataset"] or "").split(" && "):
            if c.strip():
                key = tuple((re.search(rf"{f} (\S+)", c) or [None, ""])[1] for f in ("--out", "--seed"))
                unique.setdefault(key, c)
    return recorded + sum(dataset_mp(c) for c in unique.values())


def seen_mp(cmd: str | None, steps: float | None = None) -> float:
    """Megapixels of crops a `mcdenoise train` command draws (steps x batch x crop^2); a card whose
    command holds several trainings (the members of an ensemble, campaign 33) counts each."""
    if not cmd:
        return 0.0
    runs = [c for c in cmd.split("mcdenoise train")[1:]]
    if len(runs) > 1:
        return sum(seen_mp("mcdenoise train" + c) for c in runs)
    s = steps if steps is not None else _flag(cmd, "--steps", DEFAULTS["--steps"])
    return s * _flag(cmd, "--batch", DEFAULTS["--batch"]) * _flag(cmd, "--crop", DEFAULTS["--crop"]) ** 2 / 1e6


def stages(card: dict[str, Any]) -> list[dict[str, Any]]:
    """The training runs behind a card, newest first: dataset command, train command, CPU-s, steps."""
    out = []
    ds = card.get("dataset")
    tr = card.get("training") or {}
    # A dataset stopped at a deadline (campaign 13's GPU shards) records the images it holds.
    images_mp = ds.get("images_mp") if isinstance(ds, dict) else None
    out.append({"dataset": ds.get("command") if isinstance(ds, dict) else ds, "train": tr.get("command"),
                "cpu_s": tr.get("cpu_s"), "gpu_s": tr.get("gpu_s"), "steps": tr.get("steps"), "images_mp": images_mp})
    init = tr.get("init")
    while isinstance(init, dict):
        if "training" in init:  # a whole earlier card's dataset + training block
            out += stages({"dataset": init.get("dataset"), "training": init["training"]})
            break
        out.append({"dataset": init.get("dataset"), "train": init.get("train"), "cpu_s": init.get("cpu_s"),
                    "gpu_s": init.get("gpu_s"), "steps": None, "images_mp": None})
        init = init.get("init")
    return out


def versions(path: str) -> list[tuple[str, dict[str, Any]]]:
    """(commit, card) for every committed version of ``path``, oldest first, plus the working copy."""
    revs = subprocess.run(["git", "log", "--format=%h", "--", path], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.split()
    out = []
    for h in reversed(revs):
        try:
            text = subprocess.run(["git", "show", f"{h}:{path}"], cwd=ROOT, capture_output=True, text=True,
                                  check=True).stdout
            out.append((h, json.loads(text)))
        except (subprocess.CalledProcessError, ValueError):
            continue
    if (ROOT / path).is_file():
        out.append(("work", json.loads((ROOT / path).read_text())))
    return out


def points(spp: int) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for card_path in sorted((ROOT / SHIPPED).glob("*.json")):
        rel = f"{SHIPPED}/{card_path.name}"
        at: dict[str, int] = {}  # weights -> their row
        for commit, card in versions(rel):
            v = ((card.get("validation") or {}).get("spp") or {}).get(str(spp)) or {}
            model, oidn = (v.get("model") or {}).get("relmse"), (v.get("oidn-high") or {}).get("relmse")
            sha = card.get("weights_sha256")
            if model is None:
                continue  # no third-party block
            st = stages(card)
            row = {
                "model": card_path.stem, "commit": commit, "relmse": model, "oidn": oidn,
                "cpu_h": sum(s["cpu_s"] or 0.0 for s in st) / 3600,
                "gpu_h": sum(s.get("gpu_s") or 0.0 for s in st) / 3600,
                "dataset_mp": chain_dataset_mp(st),
                "seen_mp": sum(seen_mp(s["train"], s["steps"]) for s in st),
                "stages": len(st),
            }
            if sha in at:
                # The same weights annotated again: the newest annotation counts (a rule set after
                # training, such as a clamp, changes the weights' file before its card is re-annotated).
                rows[at[sha]] = row
            else:
                at[sha] = len(rows)
                rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spp", type=int, default=8)
    ap.add_argument("--out", default="docs/img/training_evidence.png")
    a = ap.parse_args()
    rows = points(a.spp)
    print(f"| model | card version | stages | training CPU-h | GPU-h | dataset MP | seen MP | relMSE at {a.spp} spp | x OIDN high |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        ratio = r["relmse"] / r["oidn"] if r["oidn"] else float("nan")
        print(f"| {r['model']} | {r['commit']} | {r['stages']} | {r['cpu_h']:.2f} | {r['gpu_h']:.2f} | {r['dataset_mp']:.1f} | "
              f"{r['seen_mp']:.0f} | {r['relmse']:.4f} | {ratio:.2f} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4), sharey=True)
    for ax, key, label in zip(axes, ("cpu_h", "dataset_mp", "seen_mp"),
                              ("training CPU-hours (chain, cumulative)", "dataset megapixels (chain)",
                               "megapixels of crops seen (chain)")):
        for model in sorted({r["model"] for r in rows}):
            # GPU-trained versions have no place on the CPU-hours axis (the table gives their GPU-h).
            rs = sorted((r for r in rows if r["model"] == model and (key != "cpu_h" or not r["gpu_h"])), key=lambda r: r[key])
            if not rs:
                ax.plot([], [], "o-", label=model)
                continue
            ax.plot([r[key] for r in rs], [r["relmse"] for r in rs], "o-", label=model)
        oidn = [r["oidn"] for r in rows if r["oidn"]]
        if oidn:
            ax.axhline(sum(oidn) / len(oidn), color="k", ls="--", lw=1, label="OIDN 2.5.1 high")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"third-party relMSE, {a.spp} spp (mean of 9 scenes)")
    axes[-1].legend(fontsize=8)
    fig.suptitle("Each point is one shipped version of a model (its card in git history)")
    fig.tight_layout()
    out = ROOT / a.out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(out)
    print(f"\nwrote {a.out}")


if __name__ == "__main__":
    main()
