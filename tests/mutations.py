"""Mutation runner: does the test suite notice when a model is quietly broken? (issue 8, item 13)

Each mutation below is a small source patch that breaks one model the way a plausible bug would
(a U-Net step skipped, a head ignoring its context, scene features zeroed...) while everything
still runs and produces finite images of the right shape. For each one the runner

1. copies the working tree (tracked and untracked, not ignored files: ``git ls-files -co
   --exclude-standard``) to a temporary folder -- the working tree itself is never touched;
2. applies the patch there; an anchor that does not match exactly the expected number of times is
   reported loudly as ``ANCHOR`` (the code moved: update the mutation), never skipped;
3. runs the model family's test files (``tests/test_model_<family>*.py``) plus
   ``tests/test_models_common.py`` and ``tests/test_model_invariants.py`` (plus the mutation's own
   ``extra_tests``, e.g. ``tests/test_ops_kernels.py`` for a patch of an op) in the copy, with
   ``PYTHONPATH`` pointing at the copy (the copy's ``mcdenoise`` is checked to be the one imported);
4. prints one line: ``KILLED`` with the failing tests, or ``SURVIVED``.

Before the mutations, the unmutated copy runs the same test files: if that baseline fails, no
verdict means anything and the runner stops. Exit status: 0 when every mutation was killed, 1 when
any survived or any anchor no longer matches, 2 when the baseline fails or a patch does not compile.

Run from the repository root (about 1-2 minutes per mutation on 2 idle cores, 2 at a time)::

    .venv/bin/python tests/mutations.py                 # all mutations, 2 workers
    .venv/bin/python tests/mutations.py --list          # names and what each one breaks
    .venv/bin/python tests/mutations.py --check-anchors # only check that every patch applies
    .venv/bin/python tests/mutations.py sbmc_first_unet_step_only kpcn_relu_on_kernel_logits
    .venv/bin/python tests/mutations.py --workers 1 regress_bug1_splat_neighbourhood_shift
    .venv/bin/python tests/mutations.py --first-failure # stop each run at its first failing test
    .venv/bin/python tests/mutations.py --tests tests/test_models_common.py  # what one file catches

Limits: only the listed test files run, without ``slow`` tests (the project's default marker
expression). A test that starts a Python subprocess with its own ``PYTHONPATH`` would import the
working tree instead of the copy; none of the test files run here does.
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
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: Test files every mutation runs, besides its family's ``tests/test_model_<family>*.py``.
COMMON_TESTS = ("tests/test_models_common.py", "tests/test_model_invariants.py")
MAX_WORKERS = 2


@dataclass(frozen=True)
class Edit:
    """Replace ``old`` by ``new`` in ``path`` (relative to the repository root).

    ``old`` is exact text unless ``regex``; it must match exactly ``count`` times, every match is
    replaced.
    """

    path: str
    old: str
    new: str
    count: int = 1
    regex: bool = False


@dataclass(frozen=True)
class Mutation:
    """``edits`` applied together; the tests run are the family's, the common ones and ``extra_tests``
    (test files of the ops a patch touches, which the family's own files may not exercise)."""

    name: str
    what: str
    family: str
    edits: tuple[Edit, ...]
    extra_tests: tuple[str, ...] = ()


SBMC, LAYER, LAYER_CONFIG, KPCN, WSKP, WSKP_MR, BLOCKS = (
    f"mcdenoise/models/{m}.py" for m in ("sbmc", "layer", "layer_config", "kpcn", "wskp", "wskp_mr", "blocks")
)
KERNELS, IMPORTANCE, TEMPORAL = (f"mcdenoise/ops/{m}.py" for m in ("kernels", "importance_fast", "temporal"))

#: The mutations of issue 8 item 13 (each passed the whole suite when the audit ran), in its order.
#: Where the issue names no model, each model that has the mechanism gets its own mutation.
MUTATIONS: tuple[Mutation, ...] = (
    Mutation(
        "sbmc_first_unet_step_only",
        "SBMC runs only the first of its U-Net steps",
        "sbmc",
        (Edit(SBMC, "zip(self.unets, self.embeds)", "zip(self.unets[:1], self.embeds[:1])", count=2),),
    ),
    Mutation(
        "sbmc_kernel_head_ignores_context",
        "the SBMC kernel head ignores the context (it is given 0 at every call)",
        "sbmc",
        (
            Edit(
                SBMC,
                "        self.kernel = FCStack(d, hidden + [k2], context_channels=d, last_activation=False)\n",
                "        self.kernel = FCStack(d, hidden + [k2], context_channels=d, last_activation=False)\n"
                "        _fwd = self.kernel.forward\n"
                "        self.kernel.forward = lambda x, context=None: _fwd(x, None if context is None else 0 * context)\n",
            ),
        ),
    ),
    Mutation(
        "sbmc_scene_features_zeroed",
        "scene features zeroed (SBMC)",
        "sbmc",
        (Edit(SBMC, "g = signed_log1p(scene.to(f.dtype))", "g = 0 * signed_log1p(scene.to(f.dtype))"),),
    ),
    Mutation(
        "layer_scene_features_zeroed",
        "scene features zeroed (layer: they reach it through the circle of confusion)",
        "layer",
        (Edit(LAYER, "scene = scene.to(d.dtype)", "scene = 0 * scene.to(d.dtype)"),),
    ),
    Mutation(
        "kpcn_relu_on_kernel_logits",
        "ReLU on KPCN's kernel logits",
        "kpcn",
        (
            Edit(
                KPCN,
                "out[name] = apply_kernels(x[:, :3], z, self.config.kernel_size)",
                "out[name] = apply_kernels(x[:, :3], torch.relu(z), self.config.kernel_size)",
            ),
        ),
    ),
    Mutation(
        "layer_unet_skips_zeroed",
        "layer U-Net skip connections zeroed (the shared U-Net block: SBMC's too)",
        "layer",
        (Edit(BLOCKS, "torch.cat([y, skip], dim=1)", "torch.cat([y, torch.zeros_like(skip)], dim=1)"),),
    ),
    Mutation(
        "layer_unet_one_level_shallower",
        "layer U-Net one level shallower (the coarsest level of the paper preset removed)",
        "layer",
        (
            Edit(LAYER_CONFIG, "= ((64, 64), (128,), (256,), (512,), (512,))", "= ((64, 64), (128,), (256,), (512,))"),
            Edit(
                LAYER_CONFIG,
                "= ((512, 512), (256, 256), (128, 128), (128, 128), (128, 128))",
                "= ((256, 256), (128, 128), (128, 128), (128, 128))",
            ),
        ),
    ),
    Mutation(
        "layer_kernel_generator_ignores_embedding",
        "the layer kernel generator ignores the layer embedding (all three layer models)",
        "layer",
        (
            Edit(LAYER, "self.kernel_gen(l_emb, ctx)", "self.kernel_gen(0 * l_emb, ctx)"),
            Edit(LAYER, "self.kernel_gens[i](emb, c)", "self.kernel_gens[i](0 * emb, c)"),
        ),
    ),
    Mutation(
        "layer_partitioner_ignores_context",
        "the partitioner ignores the context",
        "layer",
        (Edit(LAYER, "self.partitioner(e, ctx)", "self.partitioner(e, 0 * ctx)"),),
    ),
    Mutation(
        "sbmc_radiance_not_log_compressed",
        "radiance fed without log compression (SBMC)",
        "sbmc",
        (Edit(SBMC, '_LOG_CHANNELS = frozenset({"radiance", ', "_LOG_CHANNELS = frozenset({"),),
    ),
    Mutation(
        "layer_radiance_not_log_compressed",
        "radiance fed without log compression (layer)",
        "layer",
        (Edit(LAYER, '_LOG_CHANNELS = frozenset({"radiance", ', "_LOG_CHANNELS = frozenset({"),),
    ),
    Mutation(
        "wskp_repvgg_identity_removed",
        "RepVGG identity branch removed",
        "wskp",
        (
            Edit(
                WSKP,
                "self.identity = nn.BatchNorm2d(out_ch) if in_ch == out_ch else None",
                "self.identity = None",
            ),
        ),
    ),
    Mutation(
        "wskp_mr_coarse_levels_dropped",
        "wskp_mr coarse levels dropped (the finest level's result is returned as is)",
        "wskp",
        (Edit(WSKP_MR, "result = multires_blend(fine, result, alpha)", "result = fine"),),
    ),
    Mutation(
        "wskp_mr_blend_weight_raw_logit",
        "wskp_mr blend weight left as a raw logit (no sigmoid)",
        "wskp",
        (Edit(WSKP_MR, "torch.sigmoid(z[:, 2 * n : 2 * n + 1])", "z[:, 2 * n : 2 * n + 1]"),),
    ),
    # Extra mutations beyond the list: variants that break one code path only, and
    # regressions that put back the bugs issue 8 reported as fixed (bugs 1, 3 and 4). They were kept
    # in benchmarks/mutate_sbmc.py and benchmarks/mutate_wskp.py before those merged into this file.
    Mutation(
        "sbmc_first_unet_step_only_inference",
        "SBMC runs only the first U-Net step in the banded inference loop (training path intact)",
        "sbmc",
        (
            Edit(
                SBMC,
                "            ctx = unet(e.mean(dim=1))\n            for y0",
                "            ctx = unet(e.mean(dim=1)) if ctx.numel() == 0 else ctx\n            for y0",
            ),
        ),
    ),
    Mutation(
        "sbmc_kernel_head_built_without_context",
        "the SBMC kernel head is built without a context input (so it silently ignores the context)",
        "sbmc",
        (Edit(SBMC, "hidden + [k2], context_channels=d,", "hidden + [k2], context_channels=0,"),),
    ),
    Mutation(
        "sbmc_radiance_split_not_log_compressed",
        "radiance and its diffuse/specular split fed without log compression (SBMC)",
        "sbmc",
        (Edit(SBMC, '_LOG_CHANNELS = frozenset({"radiance", "diffuse", "specular", ', "_LOG_CHANNELS = frozenset({"),),
    ),
    Mutation(
        "wskp_repvgg_identity_removed_forward_only",
        "RepVGG identity branch skipped in the unfused forward only (reparameterize() still folds it)",
        "wskp",
        (Edit(WSKP, "                y = y + self.identity(x)", "                y = y"),),
    ),
    Mutation(
        "regress_bug1_splat_neighbourhood_shift",
        "issue 8 bug 1 back: splat shift = max of any sample's logits within K x K of the destination",
        "sbmc",
        (
            Edit(
                KERNELS,
                "        plane = destination_max(logits, k)\n",
                "        plane = destination_max(logits.amax(2, keepdim=True).expand_as(logits), k)\n",
            ),
        ),
        extra_tests=("tests/test_ops_kernels.py",),
    ),
    Mutation(
        "regress_bug1_gather_max_over_outside_taps",
        "issue 8 bug 1 (gather form) back: per-pixel shift taken over taps that read outside the image",
        "sbmc",
        (Edit(KERNELS, '.masked_fill(~inside, float("-inf")).amax(dim=1)', ".amax(dim=1)"),),
        extra_tests=("tests/test_ops_kernels.py",),
    ),
    Mutation(
        "regress_bug3_importance_image_wide_shift",
        "issue 8 bug 3 back: importance sums shifted by the image-wide max instead of per window",
        "wskp",
        (
            Edit(
                IMPORTANCE,
                "    shift = F.max_pool2d(log_w.detach(), kernel, stride=1, padding=padding)",
                "    shift = log_w.detach().amax(dim=(-2, -1), keepdim=True).expand_as(log_w)",
            ),
        ),
        extra_tests=("tests/test_ops_importance.py",),
    ),
    Mutation(
        "regress_bug4_demodulate_albedo_plus_eps",
        "issue 8 bug 4 back: WSKP demodulates by albedo + eps instead of the effective albedo",
        "wskp",
        (Edit(WSKP, "    return torch.maximum(a, 1 - a / threshold)", "    return albedo + 0.00316"),),
    ),
    Mutation(
        "temporal_fixed_alpha",
        "temporal blend uses the fixed alpha from the first frame on (history length ignored)",
        "wskp",
        (Edit(TEMPORAL, "    return torch.clamp(1.0 / n, min=alpha)", "    return torch.full_like(n, alpha)"),),
        extra_tests=("tests/test_temporal.py",),
    ),
)


class AnchorError(Exception):
    """A mutation's anchor text does not match its expected number of times: the code moved."""


def patched(text: str, edit: Edit) -> str:
    """``text`` with ``edit`` applied; raises :class:`AnchorError` on a wrong match count."""
    pattern = edit.old if edit.regex else re.escape(edit.old)
    found = len(re.findall(pattern, text))
    if found != edit.count:
        raise AnchorError(
            f"{edit.path}: anchor {edit.old!r} found {found} time(s), expected {edit.count}: "
            f"the code moved, update this mutation"
        )
    if edit.regex:
        return re.sub(pattern, edit.new, text)
    return text.replace(edit.old, edit.new)


def apply(mutation: Mutation, root: Path) -> None:
    """Apply every edit of ``mutation`` to the files under ``root``; checks that they compile."""
    texts: dict[str, str] = {}
    for edit in mutation.edits:
        if edit.path not in texts:
            file = root / edit.path
            if not file.is_file():
                raise AnchorError(f"{edit.path}: file not found")
            texts[edit.path] = file.read_text()
        texts[edit.path] = patched(texts[edit.path], edit)
    for path, text in texts.items():
        compile(text, path, "exec")  # SyntaxError: a broken patch, not a killed mutation
        (root / path).write_text(text)


def source_files() -> list[str]:
    """Files of the working tree: tracked and untracked, without ignored ones."""
    out = subprocess.run(
        ["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True, capture_output=True
    ).stdout
    return [p for p in out.decode().split("\0") if p and (ROOT / p).is_file()]


def make_copy(dst: Path, files: list[str]) -> None:
    for rel in files:
        target = dst / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, target)


def test_files(family: str, files: list[str]) -> list[str]:
    own = sorted(f for f in files if re.fullmatch(rf"tests/test_model_{re.escape(family)}[a-z0-9_]*\.py", f))
    return own + [f for f in COMMON_TESTS if f in files]


def mutation_tests(m: Mutation, files: list[str]) -> list[str]:
    """The family's and common test files, then ``m.extra_tests`` (a missing one is an anchor error)."""
    missing = [t for t in m.extra_tests if t not in files]
    if missing:
        raise AnchorError(f"extra test file(s) {missing} not found: update this mutation")
    base = test_files(m.family, files)
    return base + [t for t in m.extra_tests if t not in base]


def _env(copy: Path, threads: int) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(copy), PYTHONDONTWRITEBYTECODE="1")
    # Two pytest processes on 2 cores: one thread each, or they spin against each other.
    env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    return env


def check_import(copy: Path, threads: int) -> None:
    """The copy's ``mcdenoise`` must be the one imported, not the editable install's."""
    got = subprocess.run(
        [sys.executable, "-c", "import mcdenoise, sys; sys.stdout.write(mcdenoise.__file__)"],
        cwd=copy, env=_env(copy, threads), capture_output=True, text=True, check=True,
    ).stdout
    if not Path(got).resolve().is_relative_to(copy.resolve()):
        raise SystemExit(f"mutations: the copy imports mcdenoise from {got}, not from {copy}; refusing to run")


@dataclass
class Outcome:
    verdict: str  # KILLED, SURVIVED, ANCHOR, ERROR
    detail: str
    seconds: float = 0.0


def _short(failed: list[str], keep: int = 4) -> str:
    """The first ``keep`` failing test ids, without the ``tests/`` prefix."""
    names = [f.removeprefix("tests/") for f in failed]
    return ", ".join(names[:keep]) + (f" (+{len(names) - keep} more)" if len(names) > keep else "")


def run_pytest(copy: Path, tests: list[str], *, first_failure: bool, timeout: float, threads: int) -> Outcome:
    cmd = [sys.executable, "-m", "pytest", "-q", "-rfE", "-p", "no:cacheprovider", "--no-header", *tests]
    if first_failure:
        cmd.insert(3, "-x")
    t0 = time.monotonic()
    try:
        proc = subprocess.run(cmd, cwd=copy, env=_env(copy, threads), capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return Outcome("KILLED", f"timed out after {timeout:.0f} s (a hang counts as noticed)", time.monotonic() - t0)
    dt = time.monotonic() - t0
    failed = [ln.split(" ", 1)[1].split(" - ")[0] for ln in proc.stdout.splitlines() if ln.startswith(("FAILED ", "ERROR "))]
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else proc.stderr.strip()[-300:]
    if proc.returncode == 0:
        return Outcome("SURVIVED", summary, dt)
    if proc.returncode == 1 and failed:
        return Outcome("KILLED", f"{len(failed)} failed: " + _short(failed), dt)
    if proc.returncode == 2 and failed:  # collection errors: the mutated module does not import
        return Outcome("KILLED", "collection error: " + _short(failed), dt)
    return Outcome("ERROR", f"pytest exit {proc.returncode}: {summary}\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}", dt)


def run_one(mutation: Mutation | None, files: list[str], tests: list[str], args: argparse.Namespace,
            threads: int) -> Outcome:
    """Copy, patch (unless ``mutation`` is None: the baseline), run; the copy is removed after."""
    tmp = Path(tempfile.mkdtemp(prefix=f"mcd-mut-{mutation.name if mutation else 'baseline'}-"))
    try:
        make_copy(tmp, files)
        if mutation is not None:
            try:
                apply(mutation, tmp)
            except AnchorError as e:
                return Outcome("ANCHOR", str(e))
            except SyntaxError as e:
                return Outcome("ERROR", f"the patched source does not compile: {e}")
        check_import(tmp, threads)
        return run_pytest(tmp, tests, first_failure=args.first_failure, timeout=args.timeout, threads=threads)
    finally:
        if args.keep:
            print(f"  (kept {tmp})", flush=True)
        else:
            shutil.rmtree(tmp, ignore_errors=True)


def check_anchors() -> list[tuple[Mutation, str]]:
    """Apply every mutation to the working tree's text in memory; (mutation, problem) per failure."""
    problems = []
    files = source_files()
    for m in MUTATIONS:
        texts: dict[str, str] = {}
        try:
            mutation_tests(m, files)
            for edit in m.edits:
                file = ROOT / edit.path
                if not file.is_file():
                    raise AnchorError(f"{edit.path}: file not found")
                texts[edit.path] = patched(texts.get(edit.path) or file.read_text(), edit)
            for path, text in texts.items():
                compile(text, path, "exec")
        except (AnchorError, SyntaxError) as e:
            problems.append((m, str(e)))
    return problems


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("names", nargs="*", help="run only these mutations (default: all)")
    p.add_argument("--list", action="store_true", help="list the mutations and exit")
    p.add_argument("--check-anchors", action="store_true", help="only check that every patch applies and compiles")
    p.add_argument("--workers", type=int, default=MAX_WORKERS, help=f"parallel pytest runs (at most {MAX_WORKERS})")
    p.add_argument("--first-failure", action="store_true", help="stop each run at its first failing test (-x)")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per pytest run")
    p.add_argument("--skip-baseline", action="store_true", help="do not run the unmutated copy first")
    p.add_argument("--keep", action="store_true", help="keep the temporary copies")
    p.add_argument("--tests", nargs="+", metavar="FILE",
                   help="run these test files for every mutation instead of the family's and the common ones")
    args = p.parse_args(argv)

    if args.list:
        for m in MUTATIONS:
            print(f"{m.name:42s} [{m.family}] {m.what}")
        return 0
    if args.check_anchors:
        problems = check_anchors()
        for m, msg in problems:
            print(f"ANCHOR    {m.name}: {msg}")
        print(f"{len(MUTATIONS) - len(problems)} of {len(MUTATIONS)} mutations apply")
        return 1 if problems else 0

    known = {m.name: m for m in MUTATIONS}
    unknown = [n for n in args.names if n not in known]
    if unknown:
        p.error(f"unknown mutation(s) {unknown}; see --list")
    chosen = [known[n] for n in args.names] if args.names else list(MUTATIONS)
    workers = max(1, min(args.workers, MAX_WORKERS, len(chosen)))
    threads = 1 if workers > 1 else 2
    files = source_files()
    try:
        plan = {m.name: list(args.tests) if args.tests else mutation_tests(m, files) for m in chosen}
    except AnchorError as e:
        p.error(str(e))

    if not args.skip_baseline:
        union = sorted({t for ts in plan.values() for t in ts})
        print(f"baseline: unmutated copy, {len(union)} test files ...", flush=True)
        base = run_one(None, files, union, args, threads=2)
        if base.verdict != "SURVIVED":  # the unmutated code must pass
            print(f"BASELINE FAILS ({base.seconds:.0f} s): {base.detail}\nno mutation verdict would mean anything")
            return 2
        print(f"baseline passes ({base.seconds:.0f} s): {base.detail}", flush=True)

    results: dict[str, Outcome] = {}
    width = max(len(m.name) for m in chosen)

    def job(m: Mutation) -> None:
        out = run_one(m, files, plan[m.name], args, threads)
        results[m.name] = out
        print(f"{out.verdict:9s} {m.name:{width}s} {out.seconds:6.0f} s  {out.detail}", flush=True)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(job, chosen))

    print("\nsummary (issue 8 item 13):")
    for m in chosen:
        out = results[m.name]
        print(f"{out.verdict:9s} {m.name:{width}s} {m.what}")
    counts = {v: sum(o.verdict == v for o in results.values()) for v in ("KILLED", "SURVIVED", "ANCHOR", "ERROR")}
    print(", ".join(f"{n} {v.lower()}" for v, n in counts.items() if n))
    if counts["ERROR"]:
        return 2
    return 1 if counts["SURVIVED"] or counts["ANCHOR"] else 0


if __name__ == "__main__":
    sys.exit(main())
