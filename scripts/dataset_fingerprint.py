"""Fingerprints of rendered images, to tell whether a dataset rendered again elsewhere (another CPU,
another session) holds the same pixels: one line per image folder with the CRC-32s its meta.json
records for its per-sample data, noisy input and reference.

    python scripts/dataset_fingerprint.py data/detail_ref data/rich_val > fingerprints.txt
    python scripts/dataset_fingerprint.py data/detail_ref data/rich_val --compare fingerprints.txt

With --compare, prints how many images match, which differ and in what, and exits 1 if any differ.
Images present on one side only are listed, not counted as differing.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def fingerprints(root: Path) -> dict[str, str]:
    """``"<root name>/<image path>" -> "samples=<crc> samples_header=<crc> noisy=<crc> reference=<crc>"``
    for every image folder under ``root`` that has a meta.json with checksums."""
    out: dict[str, str] = {}
    for meta in sorted(root.rglob("meta.json")):
        if any(part.startswith(".") for part in meta.relative_to(root).parts):
            continue  # a writer's temporary folder
        doc = json.loads(meta.read_text())
        sums = doc.get("checksums")
        if not isinstance(sums, dict):
            continue
        blocks = sums.get("samples_blocks", {})
        fields = {"samples": blocks.get("crc") if isinstance(blocks, dict) else None,
                  "samples_header": sums.get("samples_header"),
                  "noisy": sums.get("noisy.exr"), "reference": sums.get("reference.exr")}
        key = f"{root.name}/{meta.parent.relative_to(root).as_posix()}"
        out[key] = " ".join(f"{k}={v}" for k, v in fields.items())
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("roots", nargs="+", type=Path)
    ap.add_argument("--compare", type=Path, help="a file this script wrote earlier")
    a = ap.parse_args()
    mine: dict[str, str] = {}
    for r in a.roots:
        if not r.is_dir():
            print(f"{r}: no such folder", file=sys.stderr)
            return 2
        mine.update(fingerprints(r))
    if a.compare is None:
        for k, v in mine.items():
            print(f"{k} {v}")
        return 0
    theirs = dict(line.split(" ", 1) for line in a.compare.read_text().splitlines() if line.strip())
    both = sorted(set(mine) & set(theirs))
    differ = [k for k in both if mine[k] != theirs[k]]
    for k in differ:
        parts = [f.split("=")[0] for f, g in zip(mine[k].split(), theirs[k].split()) if f != g]
        print(f"differs: {k} ({', '.join(parts)})")
    for k in sorted(set(mine) ^ set(theirs)):
        print(f"only {'here' if k in mine else 'in ' + str(a.compare)}: {k}")
    print(f"{len(both) - len(differ)} of {len(both)} images identical, {len(differ)} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
