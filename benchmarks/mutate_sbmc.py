"""Apply deliberate bugs (mutations) to the SBMC family in a scratch copy and check a test fails.

Issue 8 item 13 listed mutations that passed the whole suite; this reruns them (and a few
variants) so the answer stays checkable. Each mutation is a literal text substitution in a copy of
``mcdenoise/`` and ``tests/`` under a temporary folder (the working tree is never touched, so it is
safe while others run tests), then ``pytest -x`` on the SBMC test files with that copy first on
``PYTHONPATH``. A mutation is *caught* when pytest fails; the first failing test is reported.

    .venv/bin/python benchmarks/mutate_sbmc.py            # all mutations
    .venv/bin/python benchmarks/mutate_sbmc.py --only scene_features_zeroed
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SBMC = "mcdenoise/models/sbmc.py"
TESTS = ["tests/test_model_sbmc.py", "tests/test_model_invariants.py", "tests/test_ops_kernels.py"]
SELECT = "sbmc or pixel or kernels"  # -k: the invariant file also has the other families' models


@dataclass(frozen=True)
class Mutation:
    name: str
    what: str
    path: str
    edits: tuple[tuple[str, str], ...]  # (old, new), every occurrence of old must exist


MUTATIONS = [
    Mutation(
        "only_first_unet_step",
        "SBMC runs only the first of its U-Net steps (training and inference loops)",
        SBMC,
        (("zip(self.unets, self.embeds)", "list(zip(self.unets, self.embeds))[:1]"),),
    ),
    Mutation(
        "only_first_unet_step_inference",
        "the same, in the banded inference loop only",
        SBMC,
        (("            ctx = unet(e.mean(dim=1))\n            for y0", "            ctx = unet(e.mean(dim=1)) if ctx.numel() == 0 else ctx\n            for y0"),),
    ),
    Mutation(
        "kernel_head_context_zeroed",
        "the SBMC kernel head ignores the context (context multiplied by 0 at every call)",
        SBMC,
        (
            ("self.kernel(e, ctx)", "self.kernel(e, 0 * ctx)"),
            ("self.kernel(e[:, s0 : s0 + chunk], ctx)", "self.kernel(e[:, s0 : s0 + chunk], 0 * ctx)"),
            ("self.kernel(e[..., y0:y1, :], ctx[..., y0:y1, :])", "self.kernel(e[..., y0:y1, :], 0 * ctx[..., y0:y1, :])"),
        ),
    ),
    Mutation(
        "kernel_head_built_without_context",
        "the SBMC kernel head is built without a context input (so it silently ignores it)",
        SBMC,
        (("hidden + [k2], context_channels=d,", "hidden + [k2], context_channels=0,"),),
    ),
    Mutation(
        "scene_features_zeroed",
        "scene features zeroed before they reach the network",
        SBMC,
        (("g = signed_log1p(scene.to(f.dtype))", "g = 0 * signed_log1p(scene.to(f.dtype))"),),
    ),
    Mutation(
        "radiance_not_log_compressed",
        "radiance (and its diffuse/specular split) fed to the network without log compression",
        SBMC,
        (('frozenset({"radiance", "diffuse", "specular", ', 'frozenset({'),),
    ),
    Mutation(
        "old_neighbourhood_shift",
        "issue 8 bug 1 back: splat shift = max of any sample within K x K of the destination",
        "mcdenoise/ops/kernels.py",
        (("        plane = destination_max(logits, k)\n", "        plane = destination_max(logits.amax(2, keepdim=True).expand_as(logits), k)\n"),),
    ),
    Mutation(
        "gather_max_over_outside_taps",
        "issue 8 bug 1 (gather form): per-pixel max taken over taps that read outside the image",
        "mcdenoise/ops/kernels.py",
        ((".masked_fill(~inside, float(\"-inf\")).amax(dim=1)", ".amax(dim=1)"),),
    ),
]


def apply(tmp: Path, m: Mutation) -> None:
    p = tmp / m.path
    text = p.read_text()
    for old, new in m.edits:
        if old not in text:
            raise SystemExit(f"{m.name}: text to mutate not found in {m.path}: {old!r} (code changed?)")
        text = text.replace(old, new)
    p.write_text(text)


def run(m: Mutation, timeout: int) -> tuple[bool, str, float]:
    with tempfile.TemporaryDirectory(prefix="mutate_sbmc_") as d:
        tmp = Path(d)
        shutil.copytree(ROOT / "mcdenoise", tmp / "mcdenoise")
        shutil.copytree(ROOT / "tests", tmp / "tests")
        shutil.copy(ROOT / "pyproject.toml", tmp / "pyproject.toml")
        apply(tmp, m)
        env = dict(os.environ, PYTHONPATH=str(tmp))
        cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", "-k", SELECT, *TESTS]
        t0 = time.time()
        try:
            out = subprocess.run(cmd, cwd=tmp, env=env, capture_output=True, text=True, timeout=timeout).stdout
        except subprocess.TimeoutExpired:
            return False, "TIMEOUT", time.time() - t0
        failed = re.findall(r"^FAILED (\S+)", out, re.M)
        return bool(failed), (failed[0] if failed else out.strip().splitlines()[-1]), time.time() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="mutation names (default: all)")
    ap.add_argument("--timeout", type=int, default=900, help="seconds per mutation")
    args = ap.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only]
    missed = 0
    for m in chosen:
        caught, by, secs = run(m, args.timeout)
        missed += not caught
        print(f"{'CAUGHT' if caught else 'MISSED'}  {m.name:34s} {secs:6.0f}s  {by}    ({m.what})", flush=True)
    sys.exit(1 if missed else 0)


if __name__ == "__main__":
    main()
