"""`mcdenoise denoise` on real file layouts, and its one-line refusals (issue 11, item 1).

Weights are random (saved as .safetensors with the metadata shipped weights carry): these tests
check plumbing, naming, tiling and error paths, not image quality.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from mcdenoise.cli.main import main
from mcdenoise.data.format import ImageMeta, write_image
from mcdenoise.eval.oidn import oidn_available
from mcdenoise.io.exr import read_exr, write_exr_raw
from mcdenoise.models import build_model, synthetic_batch

H, W = 40, 52


def _weights(path, name: str) -> str:
    torch.manual_seed(0)
    save_file(build_model(name, "small").state_dict(), str(path), metadata={"model": name, "preset": "small"})
    return str(path)


def _blender_exr(path, *, depth: bool = True, nan: int = 0, size=(H, W)) -> None:
    """A Cycles multi-layer EXR with denoising data, as Blender names its channels."""
    rng = np.random.default_rng(1)
    h, w = size
    ch = {}
    color = (rng.random((3, h, w)) * 2).astype(np.float32)
    color.reshape(-1)[:nan] = np.nan
    for c, a in zip("RGB", color):
        ch[f"ViewLayer.Noisy Image.{c}"] = a
    for c in "RGBA":  # Blender's own (denoised) image: must not be taken as the input
        ch[f"ViewLayer.Combined.{c}"] = np.full((h, w), 7.0, np.float32)
    for c in "RGB":
        ch[f"ViewLayer.Denoising Albedo.{c}"] = rng.random((h, w)).astype(np.float32)
    for c in "XYZ":
        ch[f"ViewLayer.Denoising Normal.{c}"] = (rng.random((h, w)) * 2 - 1).astype(np.float32)
    if depth:
        ch["ViewLayer.Denoising Depth.Z"] = (rng.random((h, w)) * 5).astype(np.float32)
    write_exr_raw(path, ch)


@pytest.fixture
def wskp(tmp_path):
    return _weights(tmp_path / "wskp.safetensors", "wskp")


def _err_line(capfd) -> str:
    err = capfd.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    return lines[0]


def test_blender_exr_denoises(tmp_path, wskp, capfd):
    """Catches Cycles names not reaching the model, or tiles stitched wrongly in the CLI path:
    the tiled CLI output must equal the model on the whole image."""
    src, out = tmp_path / "render.exr", tmp_path / "clean.exr"
    _blender_exr(src)
    rc = main(["denoise", str(src), "-o", str(out), "--model", wskp, "--tile", "16", "--precision", "float32",
               "--preview", str(tmp_path / "clean.png")])
    cap = capfd.readouterr()
    assert rc == 0, cap.err
    assert "channels: radiance, albedo, normal, depth" in cap.out
    got = read_exr(out)["ViewLayer.Denoised"][:3]  # a Blender file: the result is its own pass
    layers = read_exr(src)
    model = build_model("wskp", "small")
    from mcdenoise.models.weights import load_weights

    load_weights(model, wskp)
    batch = {k: torch.from_numpy(layers[k])[None] for k in ("radiance", "albedo", "normal", "depth")}
    with torch.no_grad():
        want = model.eval()(batch)[0].numpy()
    assert got.shape == (3, H, W)
    assert np.abs(got - want).max() <= 1e-4 * np.abs(want).max()
    assert (tmp_path / "clean.png").read_bytes()[:4] == b"\x89PNG"


def test_nonfinite_input_is_counted(tmp_path, wskp, capfd):
    """Catches NaN input propagating into the output, or a warning without the count."""
    src, out = tmp_path / "render.exr", tmp_path / "clean.exr"
    _blender_exr(src, nan=5)
    assert main(["denoise", str(src), "-o", str(out), "--model", wskp]) == 0
    assert "5 non-finite input value(s)" in capfd.readouterr().err
    assert np.isfinite(read_exr(out)["ViewLayer.Denoised"]).all()


def test_separate_feature_files(tmp_path, wskp, capfd):
    """Catches OIDN-style inputs (colour + --albedo/--normal files) not being combined."""
    _blender_exr(tmp_path / "all.exr")
    layers = read_exr(tmp_path / "all.exr")
    for name, chans in (("color", "RGB"), ("albedo", "RGB"), ("normal", "RGB")):
        arr = layers["radiance" if name == "color" else name]
        write_exr_raw(tmp_path / f"{name}.exr", dict(zip(chans, arr)))
    write_exr_raw(tmp_path / "depth.exr", {"Z": layers["depth"][0]})
    rc = main(["denoise", str(tmp_path / "color.exr"), "--albedo", str(tmp_path / "albedo.exr"),
               "--normal", str(tmp_path / "normal.exr"), "--depth", str(tmp_path / "depth.exr"),
               "-o", str(tmp_path / "a.exr"), "--model", wskp])
    assert rc == 0, capfd.readouterr().err
    assert main(["denoise", str(tmp_path / "all.exr"), "-o", str(tmp_path / "b.exr"), "--model", wskp]) == 0
    a, b = read_exr(tmp_path / "a.exr")["radiance"], read_exr(tmp_path / "b.exr")["ViewLayer.Denoised"][:3]
    np.testing.assert_array_equal(a, b)


def _sample_folder(tmp_path, name: str, nan: int = 0):
    """An image folder of 2 random samples of every channel model ``name`` reads (the first ``nan``
    radiance values NaN), and random weights of it."""
    torch.manual_seed(0)
    batch = synthetic_batch(build_model(name, "small"), spp=2, height=H, width=W)
    samples = {k: v[0].numpy() for k, v in batch.items() if k != "scene_features"}
    samples["radiance"].reshape(-1)[:nan] = np.nan
    meta = ImageMeta(width=W, height=H, spp=2, channels=list(samples), scene="t")
    folder = write_image(tmp_path / "img", meta=meta, samples=samples)
    return folder, _weights(tmp_path / f"{name}.safetensors", name)


def test_image_folder_feeds_sample_model(tmp_path, capfd):
    """Catches an image folder's per-sample buffers not reaching a sample model, in tiles."""
    folder, weights = _sample_folder(tmp_path, "sbmc")
    rc = main(["denoise", str(folder), "-o", str(tmp_path / "out.exr"), "--model", weights, "--tile", "24"])
    cap = capfd.readouterr()
    assert rc == 0, cap.err
    assert "(per-sample)" in cap.out and "tiles" in cap.out
    assert np.isfinite(read_exr(tmp_path / "out.exr")["radiance"]).all()
    # The same folder's noisy.exr (means and variances) feeds a pixel model.
    weights = _weights(tmp_path / "kpcn_single.safetensors", "kpcn_single")
    rc = main(["denoise", str(folder), "-o", str(tmp_path / "px.exr"), "--model", weights])
    cap = capfd.readouterr()
    assert rc == 0, cap.err
    assert "radiance_variance" in cap.out and "(per-pixel)" in cap.out


def _refused(capfd, argv, *needles) -> None:
    rc = main(argv)
    line = _err_line(capfd)
    assert rc == 1, line
    for n in needles:
        assert n in line, line


def test_missing_channels_are_named(tmp_path, wskp, capfd):
    """Catches a model run on an input without its channels (or a refusal that does not say which)."""
    _blender_exr(tmp_path / "nodepth.exr", depth=False)
    _refused(capfd, ["denoise", str(tmp_path / "nodepth.exr"), "-o", str(tmp_path / "o.exr"), "--model", wskp],
             "depth", "lacks")


def test_sample_model_on_pixels_is_refused(tmp_path, capfd):
    """Catches a sample model silently fed per-pixel data, and (issue 21) a refusal that names as
    missing the channels a Blender file has per pixel (radiance, albedo, normal, depth): it names
    the per-sample buffers and only what the file lacks even per pixel."""
    _blender_exr(tmp_path / "r.exr")
    weights = _weights(tmp_path / "layer.safetensors", "layer")
    argv = ["denoise", str(tmp_path / "r.exr"), "-o", str(tmp_path / "o.exr"), "--model", weights]
    rc = main(argv)
    line = _err_line(capfd)
    assert rc == 1 and "per-sample buffers" in line and "specular" in line, line
    named = {c.strip() for c in line.split("lacks:", 1)[1].split(",")}
    assert not named & {"radiance", "albedo", "normal", "depth"}, line


@pytest.mark.skipif(not oidn_available(), reason="needs pyoidn 2.5.1")
def test_oidn_names_the_guides_it_reads(tmp_path, capfd):
    """Catches the 'channels:' line of OIDN naming albedo and normal for a file that has neither
    (a Cycles render without Denoising Data; seen on a real one): OIDN reads the colour alone."""
    rng = np.random.default_rng(2)
    write_exr_raw(tmp_path / "r.exr", {f"ViewLayer.Noisy Image.{c}": rng.random((H, W)).astype(np.float32)
                                       for c in "RGB"})
    rc = main(["denoise", str(tmp_path / "r.exr"), "-o", str(tmp_path / "o.exr")])
    cap = capfd.readouterr()
    assert rc == 0, cap.err
    assert "channels: radiance (per-pixel)" in cap.out, cap.out
    _blender_exr(tmp_path / "full.exr")
    assert main(["denoise", str(tmp_path / "full.exr"), "-o", str(tmp_path / "o2.exr"), "--model", "oidn"]) == 0
    assert "channels: radiance, albedo, normal (per-pixel)" in capfd.readouterr().out


def test_size_mismatch(tmp_path, wskp, capfd):
    """Catches feature files of another size being cropped or broadcast instead of refused."""
    _blender_exr(tmp_path / "color.exr")
    write_exr_raw(tmp_path / "alb.exr", {c: np.ones((H + 1, W), np.float32) for c in "RGB"})
    _refused(capfd, ["denoise", str(tmp_path / "color.exr"), "--albedo", str(tmp_path / "alb.exr"),
                     "-o", str(tmp_path / "o.exr"), "--model", wskp], "size mismatch")


def test_unreadable_file(tmp_path, wskp, capfd):
    """Catches a traceback (or the OpenEXR library's own stderr lines) on a corrupt file."""
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"v/1\x01" + b"\x00" * 64)
    _refused(capfd, ["denoise", str(bad), "-o", str(tmp_path / "o.exr"), "--model", wskp], "bad.exr")


def test_existing_output_needs_force(tmp_path, wskp, capfd):
    """Catches a silent overwrite of an existing output; --force replaces it."""
    src, out = tmp_path / "r.exr", tmp_path / "o.exr"
    _blender_exr(src)
    out.write_bytes(b"keep")
    _refused(capfd, ["denoise", str(src), "-o", str(out), "--model", wskp], "already exists", "--force")
    assert out.read_bytes() == b"keep"
    assert main(["denoise", str(src), "-o", str(out), "--model", wskp, "--force"]) == 0


def test_output_is_never_the_input(tmp_path, wskp, capfd):
    """Catches the input being destroyed, even with --force and through another spelling of its path."""
    src = tmp_path / "r.exr"
    _blender_exr(src)
    before = src.read_bytes()
    other = tmp_path / "sub" / ".." / "r.exr"
    (tmp_path / "sub").mkdir()
    _refused(capfd, ["denoise", str(src), "-o", str(other), "--model", wskp, "--force"], "overwrite the input")
    assert src.read_bytes() == before


def test_force_never_writes_into_an_input_folder(tmp_path, capfd):
    """Catches issue 22 item 1: `denoise r -o r/noisy.exr --force` overwrote the folder's own noisy.exr,
    and `--preview r/samples.bin --force` turned samples.bin into a PNG; a new name inside the folder,
    an input EXR's own image folder and the weights file are refused too."""
    torch.manual_seed(0)
    model = build_model("sbmc", "small")
    batch = synthetic_batch(model, spp=2, height=H, width=W)
    samples = {k: v[0].numpy() for k, v in batch.items() if k != "scene_features"}
    folder = write_image(tmp_path / "img", meta=ImageMeta(width=W, height=H, spp=2, channels=list(samples), scene="t"),
                         samples=samples)
    weights = _weights(tmp_path / "sbmc.safetensors", "sbmc")
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    out = str(tmp_path / "x.exr")
    cases = [
        ["-o", str(folder / "noisy.exr")],
        ["-o", out, "--preview", str(folder / "samples.bin")],
        ["-o", str(folder / "new.exr")],
        ["-o", str(tmp_path / "img" / "." / "sub.exr")],
        ["-o", out, "--preview", weights],
    ]
    for extra in cases:
        _refused(capfd, ["denoise", str(folder), "--model", weights, "--force", *extra], "input")
    # An input EXR that sits in an image folder: the folder is not written to either.
    _refused(capfd, ["denoise", str(folder / "noisy.exr"), "--model", weights, "--force",
                     "-o", str(folder / "clean.exr")], "inside the input folder")
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert not (tmp_path / "x.exr").exists()


def test_max_memory_below_the_minimum_tile_is_refused(tmp_path, wskp, capfd):
    """Catches issue 22 item 7: `--max-memory 1K` silently planned 1-px tiles (16,384 tiles, 65x
    slower); it must be one line naming the minimum, and that minimum must then be accepted."""
    import re

    src = tmp_path / "r.exr"
    _blender_exr(src, size=(128, 128))
    argv = ["denoise", str(src), "--model", wskp, "--precision", "float32"]
    _refused(capfd, [*argv, "-o", str(tmp_path / "a.exr"), "--max-memory", "1K"], "--max-memory", "minimum", "at least")
    rc = main([*argv, "-o", str(tmp_path / "a.exr"), "--max-memory", "1K"])
    minimum = re.search(r"at least --max-memory (\d+M)", capfd.readouterr().err).group(1)
    assert rc == 1
    rc = main([*argv, "-o", str(tmp_path / "b.exr"), "--max-memory", minimum])
    cap = capfd.readouterr()
    assert rc == 0, cap.err
    tiles = re.search(r"ran (\d+) tiles of (\d+) px", cap.out)
    assert tiles is None or int(tiles.group(2)) >= 32, cap.out


def _tmpfs(mnt, options: str):
    """A small tmpfs mounted at ``mnt`` (skips where mounting is not allowed); unmount with the returned call."""
    import subprocess

    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip(f"cannot mount a tmpfs ({options}) here (not root?)")
    return lambda: subprocess.run(["umount", str(mnt)], check=False)


@pytest.mark.parametrize("options,needle", [("size=1m,ro", "read-only"), ("size=64k", "disk is full")])
def test_unwritable_output_is_one_line(tmp_path, wskp, capfd, options, needle):
    """Catches issue 22 item 9: an output on a read-only or full file system ended in OpenEXR's
    RuntimeError traceback; it must be one line naming the file and the reason, leaving nothing."""
    src = tmp_path / "r.exr"
    _blender_exr(src, size=(96, 96))
    umount = _tmpfs(tmp_path / "mnt", options)
    try:
        _refused(capfd, ["denoise", str(src), "-o", str(tmp_path / "mnt" / "o.exr"), "--model", wskp], "o.exr", needle)
        assert list((tmp_path / "mnt").iterdir()) == []
    finally:
        umount()


def test_preview_failure_leaves_no_exr_and_stale_temps_go(tmp_path, wskp, capfd):
    """Catches issue 22 items 9 and 10: a preview that could not be written left the EXR behind with
    rc 1; a dead writer's `.o.tmp-*` temporary beside the output was never removed; `--device mps`
    gave a traceback."""
    import subprocess

    from mcdenoise.io import safety

    src, out = tmp_path / "r.exr", tmp_path / "o.exr"
    _blender_exr(src)
    (tmp_path / "plain").write_text("a file, not a folder")
    _refused(capfd, ["denoise", str(src), "-o", str(out), "--model", wskp, "--preview",
                     str(tmp_path / "plain" / "p.png")], "plain")
    assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = tmp_path / f".o.tmp-{safety._HOST}-{dead.pid}-0123abcd.exr"
    stale.write_bytes(b"half an EXR")
    assert main(["denoise", str(src), "-o", str(out), "--model", wskp, "--preview", str(tmp_path / "p.png")]) == 0
    assert out.is_file() and (tmp_path / "p.png").is_file() and not stale.exists()
    _refused(capfd, ["denoise", str(src), "-o", str(tmp_path / "m.exr"), "--model", wskp, "--device", "mps"],
             "--device mps", "cpu or cuda")


def test_self_ensemble_runs_eight_orientations_and_records_it(tmp_path, capfd):
    """Catches --self-ensemble being ignored (one pass, no record in the file) or changing nothing:
    the command says it ran 8 orientations, the EXR header says so, and the result differs from
    the single pass of the same (not rotation-equivariant, random-weight) model. Also catches the
    NaN count of a samples file multiplied by the 8 reads."""
    from mcdenoise.io.exr import read_exr_header

    folder, weights = _sample_folder(tmp_path, "layer", nan=3)
    outs, counts = {}, []
    for flag in ([], ["--self-ensemble"]):
        out = tmp_path / f"out{len(flag)}.exr"
        rc = main(["denoise", str(folder), "-o", str(out), "--model", weights, "--precision", "float32", *flag])
        cap = capfd.readouterr()
        assert rc == 0, cap.err
        assert ("8 orientations" in cap.out) == bool(flag)
        warned = [ln.split(": ")[-1] for ln in cap.err.splitlines() if "non-finite" in ln]
        assert len(warned) == 1, cap.err
        counts.append(warned[0])  # e.g. "9 non-finite input value(s) ...": the samples' and noisy.exr's
        assert ("mcdenoise_self_ensemble" in read_exr_header(out)) == bool(flag)
        outs[bool(flag)] = read_exr(out)["radiance"]
    assert counts[0] == counts[1], counts  # counted once, not once per orientation
    assert np.isfinite(outs[True]).all()
    assert np.abs(outs[True] - outs[False]).max() > 1e-3 * np.abs(outs[False]).max()


@pytest.mark.skipif(not oidn_available(), reason="pyoidn not installed")
def test_self_ensemble_with_oidn_says_it_was_not_applied(tmp_path, capfd):
    """Catches --self-ensemble silently doing nothing: OIDN runs once, and the command says so
    instead of leaving the user to believe the output is an ensemble."""
    _blender_exr(tmp_path / "full.exr")
    rc = main(["denoise", str(tmp_path / "full.exr"), "-o", str(tmp_path / "o.exr"), "--model", "oidn",
               "--self-ensemble"])
    out = capfd.readouterr().out
    assert rc == 0 and "self-ensemble: not applied" in out and "orientations" not in out
