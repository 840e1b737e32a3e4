"""Apply deliberate mutations to the WSKP family and check that the test suite notices each one.

Issue 8 item 13 lists mutations that once passed the whole suite; this script re-applies the ones
touching ``wskp`` / ``wskp_mr`` (plus the bugs 3 and 4 fixes undone) and runs the tests that should
catch them.  Each mutation runs in a throw-away copy of the package and tests (the checkout is never
edited, so it can run while others work), with that copy first on ``PYTHONPATH``.

    .venv/bin/python benchmarks/mutate_wskp.py            # all mutations, one line each
    .venv/bin/python benchmarks/mutate_wskp.py --list
    .venv/bin/python benchmarks/mutate_wskp.py identity   # the mutations whose name contains it
    .venv/bin/python benchmarks/mutate_wskp.py wskp_mr --all-failures --tests tests/test_model_wskp.py

Exit status 0 when the unmutated copy passes and every mutation makes at least one test fail.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Tests that should catch the mutations below (kept small: each mutation runs all of them).
TESTS = [
    "tests/test_model_wskp.py",
    "tests/test_ops_importance.py",
    "tests/test_temporal.py",
] + [
    f"tests/test_model_invariants.py::test_constant_image_stays_constant[{name}-{factor}]"
    for name in ("wskp", "wskp_mr") for factor in ("1.0", "2.0", "3.0")
]


@dataclass
class Mutation:
    """Replace ``old`` by ``new`` in ``path`` (relative to the repository root); ``old`` must occur."""

    name: str
    path: str
    old: str
    new: str


MUTATIONS = [
    Mutation(
        "repvgg identity branch removed (constructor)",
        "mcdenoise/models/wskp.py",
        "self.identity = nn.BatchNorm2d(out_ch) if in_ch == out_ch else None",
        "self.identity = None",
    ),
    Mutation(
        "repvgg identity branch removed (forward only)",
        "mcdenoise/models/wskp.py",
        "                y = y + self.identity(x)",
        "                y = y",
    ),
    Mutation(
        "wskp_mr coarse levels dropped",
        "mcdenoise/models/wskp_mr.py",
        "            result = multires_blend(fine, result, alpha)  # type: ignore[arg-type]",
        "            result = fine",
    ),
    Mutation(
        "wskp_mr blend weight left as a raw logit",
        "mcdenoise/models/wskp_mr.py",
        "torch.sigmoid(z[:, 2 * n : 2 * n + 1])",
        "z[:, 2 * n : 2 * n + 1]",
    ),
    Mutation(
        "bug 4 back: demodulate by albedo + eps",
        "mcdenoise/models/wskp.py",
        "    return torch.maximum(a, 1 - a / threshold)",
        "    return albedo + 0.00316",
    ),
    Mutation(
        "bug 3 back: image-wide shift instead of per-window",
        "mcdenoise/ops/importance.py",
        "    shift = F.max_pool2d(log_w.detach(), kernel, stride=1, padding=padding)",
        "    shift = log_w.detach().amax(dim=(-2, -1), keepdim=True).expand_as(log_w)",
    ),
    Mutation(
        "temporal: fixed alpha from the first frame (no history length)",
        "mcdenoise/ops/temporal.py",
        "    return torch.clamp(1.0 / n, min=alpha)",
        "    return torch.full_like(n, alpha)",
    ),
]


def _copy_tree(dst: Path) -> None:
    for name in ("mcdenoise", "tests"):
        shutil.copytree(ROOT / name, dst / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", dst / "pyproject.toml")


def _run_tests(tree: Path, timeout: float, tests: list[str], all_failures: bool) -> tuple[int, str]:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rf", *([] if all_failures else ["-x"]), *tests]
    try:
        proc = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return -1, "timeout"
    lines = [ln.split(" - ")[0] for ln in proc.stdout.splitlines() if ln.startswith(("FAILED", "ERROR"))]
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr[-300:]
    if not lines:
        return proc.returncode, summary
    return proc.returncode, ("\n" + " " * 8).join(lines) if all_failures else lines[0]


def run(mutation: Mutation | None, timeout: float, tests: list[str], all_failures: bool = False) -> tuple[int, str]:
    """Run ``tests`` on a copy with ``mutation`` applied (None: the unmutated code)."""
    with tempfile.TemporaryDirectory(prefix="mutate_wskp_") as tmp:
        tree = Path(tmp)
        _copy_tree(tree)
        if mutation is not None:
            f = tree / mutation.path
            text = f.read_text()
            if text.count(mutation.old) != 1:
                return -2, f"mutation site not found exactly once in {mutation.path}: {mutation.old!r}"
            f.write_text(text.replace(mutation.old, mutation.new))
        # The copy, not the editable install, must be what the tests import.
        check = subprocess.run(
            [sys.executable, "-c", "import mcdenoise, sys; sys.stdout.write(mcdenoise.__file__)"],
            cwd=tree, env=dict(os.environ, PYTHONPATH=str(tree)), capture_output=True, text=True,
        )
        if not check.stdout.startswith(str(tree)):
            return -3, f"tests would import {check.stdout!r}, not the mutated copy"
        return _run_tests(tree, timeout, tests, all_failures)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("match", nargs="?", default="", help="only mutations whose name contains this")
    p.add_argument("--list", action="store_true", help="list the mutations and exit")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per test run")
    p.add_argument("--tests", nargs="+", default=TESTS, help="test paths / node ids (default: the WSKP set)")
    p.add_argument("--all-failures", action="store_true", help="list every failing test, not the first (slower)")
    args = p.parse_args(argv)
    chosen = [m for m in MUTATIONS if args.match in m.name]
    if args.list:
        for m in chosen:
            print(f"{m.name}  ({m.path})")
        return 0
    ok = True
    rc, line = run(None, args.timeout, args.tests)
    print(f"{'unmutated':<62} {'passes' if rc == 0 else 'FAILS'}  {line if rc else ''}", flush=True)
    ok &= rc == 0
    for m in chosen:
        rc, line = run(m, args.timeout, args.tests, args.all_failures)
        caught = rc > 0
        ok &= caught
        print(f"{m.name:<62} {'caught' if caught else 'NOT CAUGHT'}  {line}", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
