"""Blender Cycles files in, a Blender-ready file out (issue 21 items 1 and 3, without a real Blender).

The files are synthetic multi-layer EXRs named as Blender 4.5 writes them: passes under a
``ViewLayer.`` prefix (``Combined`` and ``Noisy Image`` RGBA, ``Denoising Normal`` XYZ,
``Denoising Albedo`` RGB, ``Denoising Depth`` Z; Cycles' ``add_pass`` calls), other passes in
half and float, a uint ID pass, Blender's string header attributes and PIZ compression.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch
from safetensors.torch import save_file

from mcdenoise.cli.main import main
from mcdenoise.eval.oidn import oidn_available
from mcdenoise.infer.sources import from_exr
from mcdenoise.io import blender
from mcdenoise.io.exr import read_exr_file, write_exr_file
from mcdenoise.models import build_model
from mcdenoise.models.weights import load_weights

H, W = 24, 28
HEADER = {"BlenderMultiChannel": "Blender V2.55.1 and newer", "Frame": "1", "Camera": "Camera",
          "Scene": "Scene", "RenderTime": "00:01.20", "Date": "2026/11/25 19:00:00",
          "compression": OpenEXR.PIZ_COMPRESSION}
#: Pixel (row, col) of a light seen in a mirror: albedo = the emission colour, normal 0.
LIGHT = (12, 14)


def blender_exr(path, *, noisy: bool = True, header: dict | None = None) -> dict[str, np.ndarray]:
    """Write a Blender 4.5-like multi-layer EXR; returns its channels as written."""
    rng = np.random.default_rng(3)
    ch: dict[str, np.ndarray] = {}
    colour = (rng.random((3, H, W)) * 2).astype(np.float32)
    colour[:, LIGHT[0], LIGHT[1]] = 900.0
    alpha = np.where(rng.random((H, W)) > 0.1, 1.0, 0.0).astype(np.float32)
    for c, a in zip("RGBA", [*colour, alpha]):
        ch[f"ViewLayer.Combined.{c}"] = (a * 0.5 if c != "A" else a).astype(np.float32)  # Blender's denoised
        if noisy:
            ch[f"ViewLayer.Noisy Image.{c}"] = a
    albedo = rng.random((3, H, W)).astype(np.float32)
    albedo[:, LIGHT[0], LIGHT[1]] = 1651.0
    normal = rng.normal(size=(3, H, W)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=0, keepdims=True)
    normal[:, LIGHT[0], LIGHT[1]] = 0.0
    for c, a in zip("RGB", albedo):
        ch[f"ViewLayer.Denoising Albedo.{c}"] = a
    for c, a in zip("XYZ", normal):
        ch[f"ViewLayer.Denoising Normal.{c}"] = a
        ch[f"ViewLayer.Normal.{c}"] = a.astype(np.float16)
    ch["ViewLayer.Denoising Depth.Z"] = (rng.random((H, W)) * 5 + 1).astype(np.float32)
    ch["ViewLayer.Depth.Z"] = ch["ViewLayer.Denoising Depth.Z"].copy()
    for c in "RGB":
        ch[f"ViewLayer.DiffCol.{c}"] = rng.random((H, W)).astype(np.float16)
    ch["ViewLayer.IndexOB.X"] = rng.integers(0, 5, (H, W)).astype(np.uint32)
    write_exr_file(path, ch, {**HEADER, **(header or {})})
    return ch


@pytest.fixture
def wskp(tmp_path):
    torch.manual_seed(0)
    path = tmp_path / "wskp.safetensors"
    save_file(build_model("wskp", "small").state_dict(), str(path), metadata={"model": "wskp", "preset": "small"})
    return str(path)


def _bits(a: np.ndarray) -> np.ndarray:
    return a.view({2: np.uint16, 4: np.uint32}[a.dtype.itemsize])


def _model_output(weights: str, path) -> np.ndarray:
    inputs = from_exr(path)
    model = build_model("wskp", "small")
    load_weights(model, weights)
    batch = {k: torch.from_numpy(inputs.pixels[k])[None] for k in ("radiance", "albedo", "normal", "depth")}
    with torch.no_grad():
        return model.eval()(batch)[0].numpy()


def _assert_kept(src: dict[str, np.ndarray], got: dict[str, np.ndarray], skip: tuple[str, ...] = ()) -> None:
    for name, arr in src.items():
        if name in skip:
            continue
        assert name in got, f"input channel {name} missing from the output"
        assert got[name].dtype == arr.dtype, f"{name}: {arr.dtype} became {got[name].dtype}"
        assert np.array_equal(_bits(got[name]), _bits(arr)), f"{name}: values changed"


def test_output_keeps_every_pass_and_adds_denoised(tmp_path, wskp, capfd):
    """Catches issue 21's output that was not a Blender file: only top-level R, G, B, every other
    pass, the alpha, the view-layer prefix and Blender's metadata dropped. Every input channel must
    survive bit for bit in its pixel type, every header attribute too, and the result is the pass
    ViewLayer.Denoised with the colour pass's alpha."""
    src, out = tmp_path / "render.exr", tmp_path / "clean.exr"
    channels = blender_exr(src)
    rc = main(["denoise", str(src), "-o", str(out), "--model", wskp, "--precision", "float32"])
    assert rc == 0, capfd.readouterr().err
    header, got = read_exr_file(out)
    _assert_kept(channels, got)
    for key, value in HEADER.items():
        assert header[key] == value, f"header {key}: {value!r} became {header.get(key)!r}"
    assert header["mcdenoise_model"] == "wskp"
    assert not {"R", "G", "B"} & set(got), "no top-level image beside the Blender passes"
    result = np.stack([got[f"ViewLayer.Denoised.{c}"] for c in "RGB"])
    np.testing.assert_allclose(result, _model_output(wskp, src), rtol=1e-5, atol=1e-6)
    assert np.array_equal(got["ViewLayer.Denoised.A"], channels["ViewLayer.Noisy Image.A"])
    # The light seen in the mirror (albedo 1651) passes through instead of exploding.
    assert np.allclose(result[:, LIGHT[0], LIGHT[1]], 900.0)


def test_replace_combined(tmp_path, wskp, capfd):
    """Catches --replace-combined writing anywhere but Combined's RGB, or dropping its alpha or
    another pass."""
    src, out = tmp_path / "render.exr", tmp_path / "clean.exr"
    channels = blender_exr(src)
    rc = main(["denoise", str(src), "-o", str(out), "--model", wskp, "--precision", "float32", "--replace-combined"])
    assert rc == 0, capfd.readouterr().err
    _, got = read_exr_file(out)
    _assert_kept(channels, got, skip=tuple(f"ViewLayer.Combined.{c}" for c in "RGB"))
    assert not any(".Denoised." in n for n in got)
    result = np.stack([got[f"ViewLayer.Combined.{c}"] for c in "RGB"])
    np.testing.assert_allclose(result, _model_output(wskp, src), rtol=1e-5, atol=1e-6)


def test_replace_combined_needs_a_blender_file(tmp_path, wskp, capfd):
    """Catches --replace-combined silently ignored on a file with no Combined pass: one line
    naming the file."""
    src = tmp_path / "plain.exr"
    write_exr_file(src, {c: np.ones((H, W), np.float32) for c in "RGB"}, {})
    rc = main(["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--model", wskp, "--replace-combined"])
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert rc != 0 and len(err) == 1 and str(src) in err[0] and "--replace-combined" in err[0]


def test_combined_is_the_colour_when_noisy_image_is_missing(tmp_path, wskp, capfd):
    """Catches issue 21's refusal of a render made with Blender's denoiser off (no Noisy Image:
    the noisy colour is Combined): Combined is read, with a one-line note; the output keeps it."""
    src, out = tmp_path / "render.exr", tmp_path / "clean.exr"
    channels = blender_exr(src, noisy=False)
    with pytest.warns(blender.BlenderNote, match="no 'Noisy Image' pass"):
        inputs = from_exr(src)
    want = np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"])
    assert np.array_equal(inputs.pixels["radiance"], want)
    rc = main(["denoise", str(src), "-o", str(out), "--model", wskp])
    err = capfd.readouterr().err
    assert rc == 0, err
    notes = [ln for ln in err.splitlines() if "Noisy Image" in ln]
    assert len(notes) == 1 and "ViewLayer.Combined" in notes[0], err
    _, got = read_exr_file(out)
    _assert_kept(channels, got)
    assert np.array_equal(got["ViewLayer.Denoised.A"], channels["ViewLayer.Combined.A"])


def test_no_colour_pass_says_what_to_do(tmp_path, wskp, capfd):
    """Catches a Blender file with no colour pass refused without saying what to enable."""
    src = tmp_path / "render.exr"
    ch = blender_exr(src)
    write_exr_file(src, {k: v for k, v in ch.items() if ".Combined." not in k and ".Noisy Image." not in k}, {})
    rc = main(["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--model", wskp])
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert rc != 0 and len(err) == 1 and str(src) in err[0] and "Combined pass" in err[0], err


def test_normals_in_world_space_when_the_header_has_the_camera(tmp_path):
    """Catches camera-space normals read as world space when the file says where the camera is
    (OpenEXR's worldToCamera), and normals changed when it does not: rotated by the camera's
    linear part (n_world = n_cam @ M3.T), length kept (coverage), zeros kept."""
    plain, rotated = tmp_path / "plain.exr", tmp_path / "rot.exr"
    ch = blender_exr(plain)
    t = 0.7
    m = np.eye(4, dtype=np.float32)
    m[:3, :3] = [[np.cos(t), 0, -np.sin(t)], [0, 1, 0], [np.sin(t), 0, np.cos(t)]]
    m[3, :3] = [1.0, 2.0, 3.0]  # the translation does not move normals
    blender_exr(rotated, header={"worldToCamera": m})
    cam = np.stack([ch[f"ViewLayer.Denoising Normal.{c}"] for c in "XYZ"])
    assert np.array_equal(from_exr(plain).pixels["normal"], cam)
    got = from_exr(rotated).pixels["normal"]
    want = np.einsum("chw,dc->dhw", cam, m[:3, :3])
    np.testing.assert_allclose(got, want, atol=1e-5)
    assert np.array_equal(got[:, LIGHT[0], LIGHT[1]], np.zeros(3, np.float32))
    half = blender.normals_to_world(cam * 0.5, m)  # a half-covered pixel keeps |n| = 0.5
    np.testing.assert_allclose(np.linalg.norm(half, axis=0), 0.5 * np.linalg.norm(cam, axis=0), rtol=1e-5)


def test_albedo_above_one_is_passed_on_unchanged(tmp_path):
    """Catches a reader that clips or zeroes Cycles' emitter albedo: OIDN gets what Blender gives
    its own OIDN, and the models' emitter rule (mcdenoise/models/emitters.py) needs the value."""
    src = tmp_path / "render.exr"
    blender_exr(src)
    assert from_exr(src).pixels["albedo"][0, LIGHT[0], LIGHT[1]] == 1651.0


def test_is_cycles_and_colour_layer():
    """The detection the reader and writer share: a view-layer prefix and a Cycles pass."""
    assert blender.is_cycles(["ViewLayer.Combined.R", "ViewLayer.Combined.A"])
    assert blender.is_cycles(["RenderLayer.Denoising Albedo.R"])
    assert not blender.is_cycles(["R", "G", "B", "albedo.R", "normal.X"])
    # Blender 5's File Output node writes passes without a view-layer prefix.
    assert blender.is_cycles(["Combined.R", "Denoising Albedo.R"])
    assert blender.colour_layer(["Combined.R", "Noisy Image.R"]) == ("", "Noisy Image")
    assert blender.colour_layer(["V.Combined.R", "V.Noisy Image.R"]) == ("V.", "Noisy Image")
    assert blender.colour_layer(["V.Combined.R"]) == ("V.", "Combined")
    assert blender.colour_layer(["R"]) is None


def test_blender_reference_without_noisy_image_converts(tmp_path):
    """Catches a Blender reference (rendered with the denoiser off: the colour is Combined) refused
    by image_from_exr with 'no radiance layer': the image folder's reference is Combined's RGB."""
    from mcdenoise.data.convert import image_from_exr
    from mcdenoise.data.format import read_image

    noisy, ref = tmp_path / "noisy.exr", tmp_path / "ref.exr"
    blender_exr(noisy)
    ch = blender_exr(ref, noisy=False)
    with pytest.warns(blender.BlenderNote):
        folder = image_from_exr([noisy], tmp_path / "img", spp=8, reference=[ref], renderer="cycles")
    got = read_image(folder).read_reference()["radiance"]
    assert np.array_equal(got, np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"]))


#: A real Cycles file: Blender 4.5.15 (bpy), ``tests/blender_scenes.py`` glass scene, 8 spp, Blender's
#: denoiser on, half-float colour passes, the 64x64 frame's 32x32 region around the 2 cm point light
#: (Blender's render region, cropped). Regenerate with ``python tests/blender_scenes.py glass OUT
#: --spp 8 --size 64 --blender-denoise --half --border 0.28125 0.78125 0.5 1.0``.
REAL = Path(__file__).parent / "fixtures" / "blender" / "glass_light_8spp.exr"
#: Highlight bound: no output value above FACTOR x the largest input value within RADIUS px, + EPS.
FACTOR, RADIUS, EPS = 2.0, 10, 0.05


def neighbourhood_max(img: np.ndarray, radius: int) -> np.ndarray:
    """Per pixel, the largest value of any channel of ``img`` (3, H, W) within ``radius`` px."""
    t = torch.from_numpy(np.ascontiguousarray(img.max(axis=0), dtype=np.float32))[None, None]
    return torch.nn.functional.max_pool2d(t, 2 * radius + 1, stride=1, padding=radius)[0, 0].numpy()


def assert_within_neighbourhood(out: np.ndarray, noisy: np.ndarray, what: str) -> None:
    """The highlight bound (issue 21): no output value above FACTOR x its input neighbourhood's
    largest value (+ EPS for dark regions)."""
    bound = FACTOR * neighbourhood_max(noisy, RADIUS) + EPS
    over = out.max(axis=0) / bound
    worst = np.unravel_index(int(np.argmax(over)), over.shape)
    assert over[worst] <= 1.0, (
        f"{what}: output {out.max(axis=0)[worst]:.4g} at pixel {worst} exceeds {FACTOR} x "
        f"{(bound[worst] - EPS) / FACTOR:.4g}, the largest input value within {RADIUS} px (+ {EPS})")


def test_real_cycles_file_conventions():
    """Catches a reader that misses Blender 4.5's conventions on a file Blender wrote: the colour is
    Noisy Image (not Blender's denoised Combined), the point light seen directly has the emission
    as albedo (> 1) and, unlike the sky, its own unit normal and depth; camera space has a surface
    facing the camera at z < 0."""
    _, ch = read_exr_file(REAL)
    px = from_exr(REAL).pixels
    noisy = np.stack([ch[f"ViewLayer.Noisy Image.{c}"] for c in "RGB"]).astype(np.float32)
    assert np.array_equal(px["radiance"], noisy)
    light = px["albedo"].max(axis=0) > 1
    assert light.sum() == 1 and px["radiance"][:, light].min() > 100, px["radiance"][:, light]
    assert np.isclose(np.linalg.norm(px["normal"][:, light]), 1.0, atol=1e-3) and px["depth"][0, light] > 0
    assert px["normal"][2, ~light].max() < 0, "camera-space normals: the wall faces the camera at z < 0"


@pytest.mark.parametrize("model", ["wskp", pytest.param("oidn", marks=pytest.mark.skipif(
    not oidn_available(), reason="needs pyoidn 2.5.1"))])
def test_real_cycles_file_point_light(tmp_path, capfd, model):
    """Catches a model that blows up a 1-px point light Cycles saw directly (albedo 634, on a wall
    it lights): shipped wskp without the emitter rule (mcdenoise/models/emitters.py) made it 7184
    from 640.5, 11x; and an output that changes a pass of Blender's file (half passes included)."""
    out_path = tmp_path / "out.exr"
    rc = main(["denoise", str(REAL), "-o", str(out_path), "--model", model])
    assert rc == 0, capfd.readouterr().err
    _, src = read_exr_file(REAL)
    _, got = read_exr_file(out_path)
    _assert_kept(src, got)
    assert set(got) - set(src) == {f"ViewLayer.Denoised.{c}" for c in "RGBA"}
    out = np.stack([got[f"ViewLayer.Denoised.{c}"] for c in "RGB"])
    noisy = np.stack([src[f"ViewLayer.Noisy Image.{c}"] for c in "RGB"]).astype(np.float32)
    assert np.isfinite(out).all()
    assert_within_neighbourhood(out, noisy, model)


def _two_view_layers(path) -> dict[str, np.ndarray]:
    """A file as Blender 4.5 writes two view layers, 'Beauty' without Denoising Data and 'Zeta'
    with it (checked on a real render: the channels are sorted by name, so 'Beauty' comes first)."""
    rng = np.random.default_rng(5)
    ch: dict[str, np.ndarray] = {}
    for layer, scale in (("Beauty", 1.0), ("Zeta", 3.0)):
        for c in "RGBA":
            ch[f"{layer}.Combined.{c}"] = np.full((H, W), scale * 0.5, np.float32)
            ch[f"{layer}.Noisy Image.{c}"] = (rng.random((H, W)) * scale).astype(np.float32)
    for c in "RGB":
        ch[f"Zeta.Denoising Albedo.{c}"] = rng.random((H, W)).astype(np.float32)
    for c in "XYZ":
        ch[f"Zeta.Denoising Normal.{c}"] = rng.normal(size=(H, W)).astype(np.float32)
    ch["Zeta.Denoising Depth.Z"] = (rng.random((H, W)) + 1).astype(np.float32)
    write_exr_file(path, ch, HEADER)
    return ch


def test_one_view_layer_is_read(tmp_path, wskp, capfd):
    """Catches colour and guides taken from different view layers (seen on a real two-layer
    Cycles render: the colour came from 'Beauty', the first by name, and albedo, normal and depth
    from 'Zeta', the only layer with Denoising Data; the result went into 'Beauty'). The layer with
    the denoising passes is read whole, with a note naming it, and the result goes beside it."""
    src, out = tmp_path / "two.exr", tmp_path / "out.exr"
    ch = _two_view_layers(src)
    with pytest.warns(blender.BlenderNote, match="reading 'Zeta'"):
        px = from_exr(src).pixels
    assert np.array_equal(px["radiance"], np.stack([ch[f"Zeta.Noisy Image.{c}"] for c in "RGB"]))
    assert np.array_equal(px["albedo"], np.stack([ch[f"Zeta.Denoising Albedo.{c}"] for c in "RGB"]))
    rc = main(["denoise", str(src), "-o", str(out), "--model", wskp, "--precision", "float32"])
    err = capfd.readouterr().err
    assert rc == 0, err
    assert len([ln for ln in err.splitlines() if "view layers" in ln]) == 1, err
    _, got = read_exr_file(out)
    _assert_kept(ch, got)
    assert set(got) - set(ch) == {f"Zeta.Denoised.{c}" for c in "RGBA"}
    names = list(ch)
    assert blender.view_layer(names) == "Zeta." and blender.colour_layer(names) == ("Zeta.", "Noisy Image")
    # Without denoising passes anywhere, the first layer by name (as Blender's file lists them).
    plain = [n for n in names if ".Denoising " not in n]
    assert blender.view_layer(plain) == "Beauty." and blender.view_layers(names) == ["Beauty.", "Zeta."]


def _with_light_passes(path, *, drop: str | None = None) -> dict[str, np.ndarray]:
    """A Blender-like file whose colour is the sum of its light passes, as Cycles writes them."""
    ch = blender_exr(path)
    rng = np.random.default_rng(5)
    dirr, ind, col = (rng.random((3, H, W)).astype(np.float32) for _ in range(3))
    gloss = rng.random((3, H, W)).astype(np.float32) * 0.3
    colour = (dirr + ind) * col + gloss
    colour[:, LIGHT[0], LIGHT[1]] = 900.0  # the light: emission, no diffuse light pass there
    dirr[:, LIGHT[0], LIGHT[1]] = ind[:, LIGHT[0], LIGHT[1]] = 0.0
    for c, i in zip("RGB", range(3)):
        ch[f"ViewLayer.Noisy Image.{c}"] = colour[i]
        for name, arr in (("DiffDir", dirr), ("DiffInd", ind), ("DiffCol", col)):
            if name != drop:
                ch[f"ViewLayer.{name}.{c}"] = arr[i]
    if drop is not None:
        for c in "RGB":
            ch.pop(f"ViewLayer.{drop}.{c}", None)
    write_exr_file(path, ch, HEADER)
    return ch


def test_light_passes_split_the_colour_into_diffuse_and_specular(tmp_path):
    """Catches Cycles' light passes used without their colour pass (they are stored divided by
    it), a split whose parts do not add up to the colour, a negative specular part from rounding,
    and a split made up when a pass is missing."""
    src = tmp_path / "render.exr"
    ch = _with_light_passes(src)
    inputs = from_exr(src)
    get = lambda n: np.stack([ch[f"ViewLayer.{n}.{c}"] for c in "RGB"]).astype(np.float32)  # noqa: E731
    colour = get("Noisy Image")
    diffuse, specular = inputs.pixels["diffuse"], inputs.pixels["specular"]
    np.testing.assert_allclose(diffuse, (get("DiffDir") + get("DiffInd")) * get("DiffCol"), rtol=1e-6)
    np.testing.assert_allclose(diffuse + specular, colour, rtol=1e-6)
    assert (specular >= 0).all() and (diffuse >= 0).all()
    assert specular[:, LIGHT[0], LIGHT[1]].min() == 900.0  # a light seen directly is specular
    # Light passes larger than the colour (half-float rounding): clipped, the sum still holds.
    split = blender.light_split({"L.DiffDir": get("DiffDir") * 2, "L.DiffInd": get("DiffInd"), "L.DiffCol": get("DiffCol")},
                                colour)
    assert split is not None and (split[1] >= 0).all() and np.allclose(split[0] + split[1], colour)
    src2 = tmp_path / "no_col.exr"
    _with_light_passes(src2, drop="DiffCol")
    assert "diffuse" not in from_exr(src2).pixels


def test_kpcn_pixel_runs_on_blender_passes_and_kpcn_refusal_says_how(tmp_path, capfd):
    """Issue 21 item 2: catches kpcn refused on a Blender file that has the light passes (the
    ``pixel`` preset needs no samples), and a refusal of the sample-variance kpcn that does not
    say what would work."""
    src = tmp_path / "render.exr"
    _with_light_passes(src)
    torch.manual_seed(0)
    weights = tmp_path / "kpcn_pixel.safetensors"
    import json
    model = build_model("kpcn", "pixel")
    save_file(model.state_dict(), str(weights), metadata={"model": "kpcn", "preset": "pixel",
                                                          "model_config": json.dumps(model.config.__dict__)})
    rc = main(["denoise", str(src), "-o", str(tmp_path / "o.exr"), "--model", str(weights)])
    assert rc == 0, capfd.readouterr().err
    _, got = read_exr_file(tmp_path / "o.exr")
    out = np.stack([got[f"ViewLayer.Denoised.{c}"] for c in "RGB"])
    assert np.isfinite(out).all() and out[:, LIGHT[0], LIGHT[1]].min() == 900.0  # the light passes through
    small = tmp_path / "kpcn_small.safetensors"
    save_file(build_model("kpcn", "small").state_dict(), str(small), metadata={"model": "kpcn", "preset": "small"})
    capfd.readouterr()
    rc = main(["denoise", str(src), "-o", str(tmp_path / "o2.exr"), "--model", str(small)])
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert rc != 0 and len(err) == 1 and "diffuse_variance" in err[0] and "kpcn-pixel" in err[0], err


def blender5_exr(path) -> dict[str, np.ndarray]:
    """Write what Blender 5's File Output node writes in multi-layer mode with docs/DENOISE.md's
    names: one part per pass, no view-layer prefix, a value pass's channel named V. Returns the
    channels of the Blender 4-like file the same pixels come from (:func:`blender_exr`)."""
    src = blender_exr(path.with_name("b4.exr"))
    parts = {}
    for name, arr in src.items():
        layer, _, comp = name.rpartition(".")
        pass_name = layer.split(".", 1)[1]
        if pass_name in ("Normal", "Depth", "IndexOB"):
            continue
        comp = "V" if pass_name == "Denoising Depth" else comp
        parts.setdefault(pass_name, {})[f"{pass_name}.{comp}"] = arr
    f = OpenEXR.File([OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION, **{k: v for k, v in HEADER.items() if k != "compression"}},
                                   ch, name=pass_name) for pass_name, ch in parts.items()])
    f.write(str(path))
    return src


def test_blender5_multipart_file(tmp_path, wskp, capfd):
    """Catches a reader that sees only the first part of a multi-part EXR or needs a view-layer
    prefix (Blender 5's recipe, docs/DENOISE.md: passes routed through a File Output node, written
    one part per pass without a prefix; before, such a file was read as its first pass alone and
    written back as bare R, G, B): the same pixels as the Blender 4 file, and an output with every
    input channel plus the Denoised pass."""
    src = blender5_exr(tmp_path / "b5.exr")
    a, b = from_exr(tmp_path / "b5.exr").pixels, from_exr(tmp_path / "b4.exr").pixels
    assert sorted(a) == sorted(b) and {"radiance", "albedo", "normal", "depth"} <= set(a)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert main(["denoise", str(tmp_path / "b5.exr"), "-o", str(tmp_path / "out.exr"), "--model", wskp]) == 0
    capfd.readouterr()
    _, got = read_exr_file(tmp_path / "out.exr")
    _, inp = read_exr_file(tmp_path / "b5.exr")
    _assert_kept(inp, got)
    assert set(got) - set(inp) == {f"Denoised.{c}" for c in "RGBA"}
    assert main(["denoise", str(tmp_path / "b4.exr"), "-o", str(tmp_path / "out4.exr"), "--model", wskp]) == 0
    capfd.readouterr()
    _, got4 = read_exr_file(tmp_path / "out4.exr")
    for c in "RGBA":
        assert np.array_equal(got[f"Denoised.{c}"], got4[f"ViewLayer.Denoised.{c}"]), c
    assert np.array_equal(got["Noisy Image.R"], src["ViewLayer.Noisy Image.R"])


def test_multipart_channel_in_two_parts_is_refused(tmp_path):
    """Catches a merge of parts that silently keeps one of two channels with the same name."""
    from mcdenoise.errors import FormatError

    px = np.ones((4, 4), np.float32)
    OpenEXR.File([OpenEXR.Part({}, {"A.R": px}, name="one"), OpenEXR.Part({}, {"A.R": px * 2}, name="two")]).write(
        str(tmp_path / "dup.exr"))
    with pytest.raises(FormatError, match="two parts"):
        read_exr_file(tmp_path / "dup.exr")
