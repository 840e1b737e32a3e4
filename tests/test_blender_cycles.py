"""Blender as a real client (issue 21 item 4): Cycles renders of small scenes built with ``bpy``,
denoised by ``mcdenoise denoise``, scored against a high-spp render of the same scene.

Slow (each scene renders 4 and 8 spp and a 1024-spp reference: 2-4 min for the file the first
time on 2 busy cores, about 10 s once cached). Needs ``bpy`` 4.5 (``pip install 'mcdenoise[blender]'``);
every test is skipped with that reason when it is absent. The scenes are built and rendered by
``tests/blender_scenes.py`` in a child process (one thread): ``bpy`` bundles its own Open Image
Denoise and TBB, which must not meet pyoidn's in this process. Renders are cached in pytest's cache
folder (``.pytest_cache/d/blender-cycles``), keyed by scene, size, spp, seed, Blender's version and
the hash of the code that builds the scene, so reruns take seconds; ``pytest --cache-clear`` renders anew.

The measured relMSE table is printed (``pytest -s``) and stored in the cache under
``blender-cycles/relmse``; docs/DENOISE.md holds the figures of the last full run.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from mcdenoise.cli.main import main
from mcdenoise.eval.metrics import relmse
from mcdenoise.eval.oidn import oidn_available, oidn_denoise
from mcdenoise.infer.sources import from_exr
from mcdenoise.io import blender
from mcdenoise.io.exr import read_exr_file
from test_blender import assert_within_neighbourhood  # the highlight bound, shared with the fast tests

#: The interpreter that renders: this one, or another with bpy (bpy 4.5 pins numpy<2; a separate
#: virtual environment keeps it away from this one's packages).
BLENDER_PYTHON = os.environ.get("MCDENOISE_BLENDER_PYTHON") or sys.executable


def _blender_version() -> str | None:
    """bpy's version in :data:`BLENDER_PYTHON`, or None when it has no bpy (not imported here)."""
    if BLENDER_PYTHON == sys.executable:
        return importlib.metadata.version("bpy") if importlib.util.find_spec("bpy") is not None else None
    try:
        done = subprocess.run([BLENDER_PYTHON, "-c", "import importlib.metadata as m; print(m.version('bpy'))"],
                              capture_output=True, text=True, timeout=60)
    except OSError:
        return None
    return done.stdout.strip() if done.returncode == 0 else None


BLENDER_VERSION = _blender_version()

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(BLENDER_VERSION is None,
                       reason=f"needs bpy 4.5 (Blender as a Python module) in {BLENDER_PYTHON}: "
                              "pip install 'mcdenoise[blender]', or set MCDENOISE_BLENDER_PYTHON to a python that has it"),
    pytest.mark.skipif(not oidn_available(), reason="needs pyoidn 2.5.1 (the OIDN baseline)"),
]

HERE = Path(__file__).resolve().parent
SCENES_PY = HERE / "blender_scenes.py"
SCENES = ("room", "dof", "glass")
SIZE = 128
SPPS = (4, 8)
REF_SPP = 1024
#: Models with random weights run only for the highlight bound (their quality means nothing).
RANDOM_MODELS = ("wskp_mr", "combine")
SHIPPED = Path(__file__).resolve().parent.parent / "mcdenoise" / "models" / "shipped"


def _scene_code(scene: str) -> str:
    """Hash of the code that builds and renders ``scene`` (tests/blender_scenes.py): a change to
    one scene renders that scene anew, not the others."""
    import inspect

    sys.path.insert(0, str(HERE))
    try:
        import blender_scenes as bs  # no bpy at import
    finally:
        sys.path.remove(str(HERE))
    parts = [bs.BUILDERS[scene], bs.render, bs.apply_recipe, bs._material, bs._checker, bs._add, bs._camera, bs._world]
    return hashlib.sha256("".join(inspect.getsource(f) for f in parts).encode()).hexdigest()[:10]


def _blender_reads(src: Path, name: str, out: Path) -> tuple[list[str], np.ndarray]:
    """``(passes Blender lists for src, pass name as Blender's compositor reads it (3, H, W))``."""
    h, w = next(iter(read_exr_file(src)[1].values())).shape
    cmd = [BLENDER_PYTHON, str(SCENES_PY), "read", str(src), name, str(out), "--size", str(w), str(h)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and out.exists(), f"Blender could not read {src}: {done.stderr[-3000:]}"
    passes = next(ln for ln in done.stdout.splitlines() if ln.startswith("passes: "))[len("passes: "):].split(";")
    _, ch = read_exr_file(out)
    return passes, _rgb(ch, "")


@pytest.fixture(scope="session")
def render(request, tmp_path_factory):
    """``render(scene, spp, seed=0, blender_denoise=False) -> Path`` of a cached Cycles render (in a
    temporary folder when pytest's cache is off, ``-p no:cacheprovider``)."""
    store = getattr(request.config, "cache", None)
    cache = Path(store.mkdir("blender-cycles")) if store is not None else tmp_path_factory.mktemp("blender-cycles")

    def _render(scene: str, spp: int, *, seed: int = 0, blender_denoise: bool = False) -> Path:
        tag = "_bd" if blender_denoise else ""
        code = _scene_code(scene)
        path = cache / f"{scene}_{SIZE}px_{spp}spp_s{seed}{tag}_bpy{BLENDER_VERSION}_{code}.exr"
        if not path.exists():
            tmp = path.with_name(f".{path.name}.{os.getpid()}.exr")
            # Light passes on: the diffuse/specular split that kpcn-pixel reads (docs/DENOISE.md).
            cmd = [BLENDER_PYTHON, str(SCENES_PY), scene, str(tmp), "--spp", str(spp), "--size", str(SIZE),
                   "--seed", str(seed), "--light-passes"] + (["--blender-denoise"] if blender_denoise else [])
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
            assert done.returncode == 0 and tmp.exists(), f"Blender render failed: {' '.join(cmd)}\n{done.stderr[-3000:]}"
            tmp.replace(path)
            for old in cache.glob(path.name.replace(f"_bpy{BLENDER_VERSION}_{code}", "_bpy*")):
                if old != path:  # the same render by older code or another Blender: stale
                    old.unlink(missing_ok=True)
        return path

    return _render


@pytest.fixture(scope="session")
def random_weights(tmp_path_factory):
    """``name -> .safetensors`` of seeded random weights for :data:`RANDOM_MODELS`."""
    from mcdenoise.models import build_model

    folder = tmp_path_factory.mktemp("random-weights")
    out = {}
    for name in RANDOM_MODELS:
        torch.manual_seed(0)
        path = folder / f"{name}.safetensors"
        save_file(build_model(name, "small").state_dict(), str(path), metadata={"model": name, "preset": "small"})
        out[name] = path
    return out


def _rgb(channels: dict[str, np.ndarray], layer: str) -> np.ndarray:
    return np.stack([channels[f"{layer}.{c}" if layer else c] for c in "RGB"]).astype(np.float32)


def _reference(path: Path) -> np.ndarray:
    """The reference colour: ``Combined`` (rendered with Blender's denoiser off)."""
    _, ch = read_exr_file(path)
    assert "ViewLayer.Noisy Image.R" not in ch
    return _rgb(ch, "ViewLayer.Combined")


def _denoise(src: Path, out: Path, capfd, *args: str) -> tuple[np.ndarray, dict[str, np.ndarray], str]:
    rc = main(["denoise", str(src), "-o", str(out), "--force", *args])
    captured = capfd.readouterr()
    assert rc == 0, captured.err
    _, ch = read_exr_file(out)
    return _rgb(ch, "ViewLayer.Denoised"), ch, captured.out


def test_the_recipe_writes_every_denoising_pass(render):
    """Catches a Blender 4.x recipe in docs/DENOISE.md that does not give the passes denoise reads:
    the render (Blender's denoiser on) has Noisy Image, Combined, Denoising Albedo/Normal/Depth under
    the view-layer prefix, and one with the denoiser off has no Noisy Image (colour in Combined)."""
    _, on = read_exr_file(render("glass", 4, blender_denoise=True))
    _, off = read_exr_file(render("glass", 4))
    for layer, comps in (("Noisy Image", "RGBA"), ("Combined", "RGBA"), ("Denoising Albedo", "RGB"),
                         ("Denoising Normal", "XYZ"), ("Denoising Depth", "Z"), ("DiffDir", "RGB"), ("DiffInd", "RGB"),
                         ("DiffCol", "RGB")):
        for c in comps:
            assert f"ViewLayer.{layer}.{c}" in on, f"ViewLayer.{layer}.{c} missing: {sorted(on)}"
    assert not any(".Noisy Image." in n for n in off) and "ViewLayer.Combined.R" in off
    inputs = from_exr(render("glass", 4, blender_denoise=True))
    assert {"radiance", "albedo", "normal", "depth", "diffuse", "specular"} <= inputs.channels("pixels")
    # The split adds up to the colour Blender wrote (Cycles' light passes are divided by DiffCol).
    np.testing.assert_allclose(inputs.pixels["diffuse"] + inputs.pixels["specular"], inputs.pixels["radiance"],
                               rtol=1e-6, atol=1e-6)
    assert float(inputs.pixels["diffuse"].mean()) > 0.05 * float(inputs.pixels["radiance"].mean())
    assert np.array_equal(inputs.pixels["radiance"], _rgb(on, "ViewLayer.Noisy Image"))
    # Blender's denoiser off: the colour is Combined, read with a note (the same samples: seed 0).
    with pytest.warns(blender.BlenderNote, match="no 'Noisy Image' pass"):
        plain = from_exr(render("glass", 4))
    assert np.array_equal(plain.pixels["radiance"], _rgb(off, "ViewLayer.Combined"))
    np.testing.assert_allclose(plain.pixels["radiance"], inputs.pixels["radiance"], rtol=1e-5, atol=1e-5)


def test_blender_opens_the_output(render, tmp_path, capfd):
    """Catches an output Blender cannot use in place of its render (issue 21, 'opens in Blender with
    every input pass still there'): Blender lists every pass of the input plus Denoised, and its
    compositor reads the result bit for bit; with --replace-combined it reads the result as Combined."""
    src = render("room", 4, blender_denoise=True)
    before, _ = _blender_reads(src, "Combined", tmp_path / "in.exr")
    out, _, _ = _denoise(src, tmp_path / "out.exr", capfd)
    after, seen = _blender_reads(tmp_path / "out.exr", "Denoised", tmp_path / "read.exr")
    assert sorted(after) == sorted(before + ["Denoised"]), (before, after)
    assert np.array_equal(seen, out), f"Blender reads Denoised differently: max diff {np.abs(seen - out).max()}"
    rc = main(["denoise", str(src), "-o", str(tmp_path / "rc.exr"), "--replace-combined"])
    assert rc == 0, capfd.readouterr().err
    after, seen = _blender_reads(tmp_path / "rc.exr", "Combined", tmp_path / "read_rc.exr")
    assert sorted(after) == sorted(before) and np.array_equal(seen, out)


#: (scene, spp) where the default pick is known to be more than 5% worse than OIDN high, and why.
#: None since campaign 14 (Blender 4.5.15; AMD EPYC, 2 cores): the default pick on these renders
#: (they have the light passes and depth) is the shipped `combine` `ens_kpcn` combiner, now with the
#: emitter mask among its inputs and 2000 more steps. On these renders (seed 0) and on eight more
#: of each (`scripts/blender_seeds.py --seeds 0,2,3,4,5,6,7,8,9`) it is at most 0.987x OIDN high
#: (glass, 8 spp, seed 0: 1.06x with campaign 10's weights); docs/models/combine.md "Campaign 14".
DEFAULT_LOSES: dict[tuple[str, int], str] = {}


@pytest.mark.parametrize("scene", SCENES)
def test_denoise_a_cycles_render(scene, render, random_weights, tmp_path, capfd, request):
    """Catches, on real Cycles renders (issue 21): a highlight blown up by a model (the bound of
    ``test_blender.assert_within_neighbourhood``, on every model that runs on Blender's passes:
    OIDN, shipped wskp, random wskp_mr and combine; shipped wskp without the emitter rule fails it
    on the room's area light, 2.1x, and on the glass scene's 1-px point light, 11.7x), a default
    pick worse than the noisy input or more than 5% worse than OIDN 2.5.1 high, and an output file
    that drops an input pass or lacks the Denoised pass."""
    ref = _reference(render(scene, REF_SPP, seed=1))
    table = {}
    for spp in SPPS:
        src = render(scene, spp, blender_denoise=True)
        _, inp = read_exr_file(src)
        noisy = _rgb(inp, "ViewLayer.Noisy Image")
        pixels = from_exr(src).pixels
        row = {"emitter_px": int((pixels["albedo"].max(axis=0) > 1).sum()), "noisy": float(relmse(noisy, ref)),
               "blender": float(relmse(_rgb(inp, "ViewLayer.Combined"), ref)),
               "oidn_pf": float(relmse(oidn_denoise(pixels["radiance"], pixels["albedo"], pixels["normal"],
                                                    prefilter="high"), ref))}
        runs = {"default": (), "oidn": ("--model", "oidn"), "wskp": ("--model", "wskp")}
        if (SHIPPED / "kpcn-pixel.safetensors").is_file():  # kpcn on Blender's light passes (issue 21 item 2)
            runs["kpcn-pixel"] = ("--model", "kpcn-pixel")
        runs.update({name: ("--model", str(path)) for name, path in random_weights.items()})
        for label, args in runs.items():
            out, got, said = _denoise(src, tmp_path / f"{label}_{spp}.exr", capfd, *args)
            assert np.isfinite(out).all(), f"{scene} {spp} spp {label}: non-finite output"
            assert_within_neighbourhood(out, noisy, f"{scene} {spp} spp {label}")
            # (iii) Every input channel is kept, and the result is added as the Denoised pass.
            assert set(inp) <= set(got), f"{label}: dropped {sorted(set(inp) - set(got))}"
            assert set(got) - set(inp) == {f"ViewLayer.Denoised.{c}" for c in "RGBA"}, sorted(set(got) - set(inp))
            if label not in random_weights:
                row[label] = float(relmse(out, ref))
            if label == "default":
                row["default_pick"] = said.split("(")[0].removeprefix("model:").strip()
        table[spp] = row
        # (ii) The default is never worse than the noisy input, and within 5% of OIDN high or better.
        assert row["default"] < row["noisy"], f"{scene} {spp} spp: default {row}"
        if (scene, spp) in DEFAULT_LOSES:  # known and stated; strict: a fix makes this fail
            assert row["default"] > 1.05 * row["oidn"], f"{scene} {spp} spp now within 5% of OIDN: drop it from DEFAULT_LOSES"
        else:
            assert row["default"] <= 1.05 * row["oidn"], f"{scene} {spp} spp: default {row}"
    # The scene exercises the emitter rule: Cycles wrote a light's or the sky's colour as albedo
    # (glass: the 2 cm light covers about half a pixel, and no sample of the 4-spp render hits it).
    assert any(row["emitter_px"] for row in table.values()), f"{scene}: no emitter pixel (albedo > 1) in view"
    if getattr(request.config, "cache", None) is not None:
        request.config.cache.set(f"blender-cycles/relmse/{scene}", {str(k): v for k, v in table.items()})
    with capfd.disabled():
        for spp, row in table.items():
            print(f"\n{scene} {spp} spp relMSE: " + ", ".join(
                f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))


#: A Python with bpy 5.x (needs Python 3.13; docs/DENOISE.md says how this project's machines get
#: one), for the Blender 5 recipe test. Unset: that test is skipped.
BLENDER5_PYTHON = os.environ.get("MCDENOISE_BLENDER5_PYTHON")


@pytest.mark.slow
@pytest.mark.skipif(not BLENDER5_PYTHON, reason="set MCDENOISE_BLENDER5_PYTHON to a Python with bpy 5.x")
def test_blender5_recipe(tmp_path, capfd):
    """Catches docs/DENOISE.md's Blender 5 recipe not giving the passes (a Blender 5 render writes
    only Combined to a multi-layer EXR; the recipe routes them through a File Output node, which
    writes one part per pass without a view-layer prefix), the reader missing any of them, a
    default result worse than the noisy input, and Blender 5 not finding every pass, and the
    result bit for bit, in our output."""
    version = subprocess.run([BLENDER5_PYTHON, "-c", "import bpy; print(bpy.app.version_string)"],
                             capture_output=True, text=True, timeout=120).stdout.strip()
    assert version.startswith("5."), f"{BLENDER5_PYTHON}: bpy {version or 'missing'}, expected 5.x"
    src, ref_path = tmp_path / "glass.exr", tmp_path / "ref.exr"
    for path, spp, seed, extra in ((src, 4, 0, ["--blender-denoise"]), (ref_path, 128, 1, [])):
        cmd = [BLENDER5_PYTHON, str(SCENES_PY), "glass", str(path), "--spp", str(spp), "--size", "64",
               "--seed", str(seed), "--light-passes", *extra]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0 and path.exists(), f"Blender 5 render failed: {' '.join(cmd)}\n{done.stderr[-3000:]}"
    _, inp = read_exr_file(src)
    passes = {name.rpartition(".")[0] for name in inp}
    assert {"Combined", "Noisy Image", "Denoising Albedo", "Denoising Normal", "Denoising Depth",
            "DiffDir", "DiffInd", "DiffCol"} <= passes, sorted(passes)
    assert {"radiance", "albedo", "normal", "depth", "diffuse", "specular"} <= set(from_exr(src).pixels)
    assert main(["denoise", str(src), "-o", str(tmp_path / "out.exr")]) == 0, capfd.readouterr().err
    capfd.readouterr()
    _, got = read_exr_file(tmp_path / "out.exr")
    assert set(inp) <= set(got) and set(got) - set(inp) == {f"Denoised.{c}" for c in "RGBA"}
    out, noisy = _rgb(got, "Denoised"), _rgb(inp, "Noisy Image")
    ref = _rgb(read_exr_file(ref_path)[1], "Combined")
    assert relmse(out, ref) < relmse(noisy, ref)
    cmd = [BLENDER5_PYTHON, str(SCENES_PY), "read", str(tmp_path / "out.exr"), "Denoised", str(tmp_path / "read.exr"),
           "--size", "64", "64"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    listed = next(ln for ln in done.stdout.splitlines() if ln.startswith("passes: "))[len("passes: "):].split(";")
    assert passes | {"Denoised"} <= set(listed), (sorted(passes), listed)
    assert np.array_equal(_rgb(read_exr_file(tmp_path / "read.exr")[1], ""), out)
