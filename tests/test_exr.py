"""EXR I/O: round trips in every naming scheme, the rename table, previews, one-line errors."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.errors import FormatError
from mcdenoise.io.exr import read_exr, read_exr_header, read_exr_raw, tonemap, write_exr, write_exr_raw, write_preview
from mcdenoise.io.names import lookup_layer, oidn_filename, parse_oidn_filename, to_exr_channel_names

H, W = 6, 9


@pytest.fixture
def layers() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    n = rng.normal(size=(3, H, W))
    return {
        "radiance": (rng.random((3, H, W)) * 50).astype(np.float32),
        "albedo": rng.random((3, H, W)).astype(np.float32),
        "normal": (n / np.linalg.norm(n, axis=0)).astype(np.float32),
        "depth": (rng.random((1, H, W)) * 10).astype(np.float32),
    }


def _exact(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert sorted(got) == sorted(want)
    for k in want:
        assert got[k].dtype == np.float32 and got[k].shape == want[k].shape, k
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def test_round_trip_ours(tmp_path: Path, layers):
    p = write_exr(tmp_path / "a.exr", dict(layers, radiance_variance=layers["radiance"] * 1e-3),
                  attributes={"spp": 8})
    raw = read_exr_raw(p)
    assert {"radiance.R", "radiance.G", "radiance.B", "normal.X", "depth.Y", "radiance_variance.B"} <= set(raw)
    got = read_exr(p)
    _exact(got, dict(layers, radiance_variance=layers["radiance"] * 1e-3))
    assert read_exr_header(p)["spp"] == 8


def test_half_only_for_half_ok(tmp_path: Path, layers):
    p = write_exr(tmp_path / "h.exr", layers, half=["albedo", "normal"])
    got = read_exr(p)
    np.testing.assert_array_equal(got["albedo"], layers["albedo"].astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(got["radiance"], layers["radiance"])
    with pytest.raises(ValueError, match="float16"):
        write_exr(tmp_path / "bad.exr", layers, half=["radiance"])
    with pytest.raises(ValueError, match="float16"):
        write_exr(tmp_path / "bad.exr", layers, half=["depth"])


def test_non_contiguous_input_is_written_correctly(tmp_path: Path):
    base = np.arange(2 * 3 * W * H, dtype=np.float32).reshape(2, 3, W, H)
    strided = base[1].transpose(0, 2, 1)  # (3, H, W), not C-contiguous
    assert not strided.flags["C_CONTIGUOUS"]
    got = read_exr(write_exr(tmp_path / "nc.exr", {"radiance": strided}))
    np.testing.assert_array_equal(got["radiance"], strided)


def test_cycles_names(tmp_path: Path, layers):
    """Names as Blender Cycles writes them: view-layer prefix, RGBA noisy image, Z depth."""
    ch = {}
    for i, c in enumerate("RGB"):
        ch[f"ViewLayer.Noisy Image.{c}"] = layers["radiance"][i]
        ch[f"ViewLayer.Denoising Albedo.{c}"] = layers["albedo"][i]
        ch[f"ViewLayer.Combined.{c}"] = layers["radiance"][i] * 0  # the denoised result: not ours
    ch["ViewLayer.Noisy Image.A"] = np.ones((H, W), np.float32)
    for i, c in enumerate("XYZ"):
        ch[f"ViewLayer.Denoising Normal.{c}"] = layers["normal"][i]
    ch["ViewLayer.Denoising Depth.Z"] = layers["depth"][0]
    p = write_exr_raw(tmp_path / "cycles.exr", ch)
    got = read_exr(p)
    assert "ViewLayer.Combined" in got  # unknown layers are kept under their own name
    del got["ViewLayer.Combined"]
    _exact(got, layers)
    assert set(read_exr(p, unknown="drop")) == set(layers)
    with pytest.raises(FormatError, match="not in the channel vocabulary"):
        read_exr(p, unknown="error")
    # Writing in the Cycles scheme and reading back is exact too.
    _exact(read_exr(write_exr(tmp_path / "c2.exr", layers, scheme="cycles")), layers)
    assert "RenderLayer.Noisy Image.R" in to_exr_channel_names("radiance", 3, "cycles", view_layer="RenderLayer")


def test_mitsuba_aov_names(tmp_path: Path, layers):
    """Names as Mitsuba 3's aov integrator writes them (aovs="dd.y:depth,nn:sh_normal,albedo:albedo")."""
    ch = {c: layers["radiance"][i] for i, c in enumerate("RGB")}
    ch.update({f"albedo.{c}": layers["albedo"][i] for i, c in enumerate("RGB")})
    ch.update({f"nn.{c}": layers["normal"][i] for i, c in enumerate("XYZ")})
    ch["dd.y.T"] = layers["depth"][0]
    ch.update({f"pos.{c}": layers["albedo"][i] * 3 for i, c in enumerate("XYZ")})
    got = read_exr(write_exr_raw(tmp_path / "mi.exr", ch))
    _exact(got, dict(layers, position=layers["albedo"] * 3))
    _exact(read_exr(write_exr(tmp_path / "mi2.exr", layers, scheme="mitsuba")), layers)


def test_pbrt_gbuffer_names(tmp_path: Path, layers):
    """Names as pbrt-v4's GBufferFilm writes them; Variance is per sample (divided by spp on request)."""
    var = (layers["radiance"] * 0.5).astype(np.float32)
    ch = {c: layers["radiance"][i] for i, c in enumerate("RGB")}
    ch.update({f"Albedo.{c}": layers["albedo"][i] for i, c in enumerate("RGB")})
    ch.update({f"Ns.{c}": layers["normal"][i] for i, c in enumerate("XYZ")})
    ch.update({f"N.{c}": layers["normal"][i] for i, c in enumerate("XYZ")})
    ch.update({f"Variance.{c}": var[i] for i, c in enumerate("RGB")})
    ch["u"] = np.zeros((H, W), np.float32)
    p = write_exr_raw(tmp_path / "pbrt.exr", ch)
    got = read_exr(p, unknown="drop")
    assert set(got) == {"radiance", "albedo", "normal"}  # no spp: Variance stays unconverted
    got = read_exr(p, spp=4, unknown="drop")
    np.testing.assert_allclose(got.pop("radiance_variance"), var / 4, rtol=1e-7)
    _exact(got, {k: layers[k] for k in ("radiance", "albedo", "normal")})
    kept = read_exr(p)
    assert kept["Variance"].shape == (3, H, W) and kept["image"].shape == (1, H, W)  # 'u' at top level


def test_oidn_file_naming(tmp_path: Path, layers):
    assert parse_oidn_filename("kitchen_0008spp.hdr.exr") == ("kitchen", 8, "hdr")
    assert parse_oidn_filename("a/b/kitchen_v2_ref.nrm.exr") == ("kitchen_v2", None, "nrm")
    assert parse_oidn_filename("kitchen.exr") is None
    assert oidn_filename("kitchen", "radiance", 8) == "kitchen_0008spp.hdr.exr"
    assert oidn_filename("kitchen", "albedo", None) == "kitchen_ref.alb.exr"
    for name in ("radiance", "albedo", "normal"):
        fn = tmp_path / oidn_filename("kitchen", name, 16)
        # OIDN files are plain RGB: the feature lives in the file name.
        write_exr_raw(fn, {c: layers[name][i] for i, c in enumerate("RGB")})
        got = read_exr(fn)
        _exact(got, {name: layers[name]})
        _exact(read_exr(write_exr(tmp_path / ("w_" + fn.name), {name: layers[name]}, scheme="oidn")), {name: layers[name]})
    assert lookup_layer("", filename="x_ref.ldr.exr").channel == "radiance"


def test_errors_are_one_line(tmp_path: Path, layers):
    p = write_exr(tmp_path / "ok.exr", layers)
    data = p.read_bytes()
    for name, content in (("trunc.exr", data[: len(data) // 2]), ("tail.exr", data[:-50]),
                          ("junk.exr", b"this is not an exr"), ("empty.exr", b"")):
        bad = tmp_path / name
        bad.write_bytes(content)
        with pytest.raises(FormatError) as err:
            read_exr(bad)
        msg = str(err.value)
        assert "\n" not in msg and str(bad) in msg and "truncated or corrupt" in msg
    with pytest.raises(FormatError, match="no such file"):
        read_exr(tmp_path / "missing.exr")
    # A vocabulary layer with the wrong components is refused, not silently reshaped.
    write_exr_raw(tmp_path / "wrong.exr", {"normal.X": layers["normal"][0], "normal.Y": layers["normal"][1]})
    with pytest.raises(FormatError, match="components"):
        read_exr(tmp_path / "wrong.exr")


def test_write_is_atomic(tmp_path: Path, layers):
    p = write_exr(tmp_path / "a.exr", layers)
    before = p.read_bytes()
    with pytest.raises(ValueError):
        write_exr(p, {"radiance": layers["radiance"], "depth": np.zeros((1, 2, 2), np.float32)})
    assert p.read_bytes() == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.exr"]


def _decode_png(path: Path) -> np.ndarray:
    """Minimal decoder for the 8-bit RGB, filter-0 PNGs write_png produces."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, size = 8, b"", None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        tag, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        assert struct.unpack(">I", data[pos + 8 + n : pos + 12 + n])[0] == zlib.crc32(tag + body) & 0xFFFFFFFF
        if tag == b"IHDR":
            size = struct.unpack(">II", body[:8])
        elif tag == b"IDAT":
            idat += body
        pos += 12 + n
    w, h = size
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(h, 1 + 3 * w)
    assert (rows[:, 0] == 0).all()
    return rows[:, 1:].reshape(h, w, 3)


@pytest.mark.parametrize(
    "kind,exposure,value,expected",
    [
        ("srgb", 0.0, 0.5, round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055))),
        ("srgb", 1.0, 0.5, 255),  # 0.5 * 2^1 = 1 -> white
        ("reinhard", 0.0, 1.0, round(255 * (1.055 * 0.5 ** (1 / 2.4) - 0.055))),  # 1/(1+1) = 0.5
        ("log", 0.0, 99.0, round(255 * np.log1p(99.0) / np.log1p(100.0))),
        ("srgb", 0.0, -3.0, 0),
    ],
)
def test_preview(tmp_path: Path, kind, exposure, value, expected):
    rgb = np.full((3, 2, 3), value, np.float32)
    rgb[:, 1, 2] = np.nan  # NaN shows black, never crashes
    p = write_preview(tmp_path / "noisy.png", rgb, exposure=exposure, tonemap=kind)
    assert p.name == f"noisy_{kind}_ev{exposure:+.1f}.png"
    img = _decode_png(p)
    assert img.shape == (2, 3, 3)
    assert int(img[0, 0, 0]) == expected
    assert int(img[1, 2, 1]) == 0
    assert tonemap(np.full((3, 1, 1), value), exposure=exposure, kind=kind)[0, 0, 0] * 255 == pytest.approx(expected, abs=0.5)
    with pytest.raises(ValueError, match="tonemap"):
        write_preview(tmp_path / "x.png", rgb, tonemap="aces")


@pytest.mark.render
def test_real_mitsuba_aov_file(tmp_path: Path):
    """An EXR written by Mitsuba 3 itself (aov integrator), in the variant the renderer uses.

    Mitsuba's variant is process-global: switching it here would break every later render test.
    """
    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "aov", "aovs": "dd.y:depth,nn:sh_normal,albedo:albedo", "img": {"type": "path"}},
        "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 6},
                   "sampler": {"type": "independent", "sample_count": 2}},
        "sphere": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.4, 0.6]}}},
        "light": {"type": "constant"},
    })
    mi.render(scene)
    path = tmp_path / "mitsuba.exr"
    scene.sensors()[0].film().bitmap().write(str(path))
    got = read_exr(path)
    assert {"radiance", "depth", "normal", "albedo"} <= set(got)
    assert got["depth"].shape == (1, 6, 8) and got["normal"].shape == (3, 6, 8)
    centre = (slice(None), 3, 4)
    assert got["depth"][centre][0] == pytest.approx(3.0, abs=0.05)  # camera at z=4, unit sphere
    np.testing.assert_allclose(got["albedo"][centre], [0.2, 0.4, 0.6], atol=1e-3)
    # Pixel-averaged normals are not unit length; at the centre the sphere faces the camera (+z).
    assert got["normal"][centre][2] > 0.9 and 0.9 < np.linalg.norm(got["normal"][centre]) <= 1.0 + 1e-5


def test_image_from_renderer_exrs(tmp_path: Path, layers):
    from mcdenoise.data.convert import image_from_exr
    from mcdenoise.data.format import read_image

    files = []
    for name in ("radiance", "albedo", "normal"):
        fn = tmp_path / oidn_filename("kitchen", name, 8)
        write_exr_raw(fn, {c: layers[name][i] for i, c in enumerate("RGB")})
        files.append(fn)
    ref = tmp_path / oidn_filename("kitchen", "radiance", None)
    write_exr_raw(ref, {c: layers["radiance"][i] * 0.5 for i, c in enumerate("RGB")})
    im = read_image(image_from_exr(files, tmp_path / "img", reference=[ref], scene="kitchen"))
    assert im.meta.spp == 8 and im.meta.channels == ["radiance", "albedo", "normal"] and im.samples is None
    _exact(im.read_noisy(), {k: layers[k] for k in ("radiance", "albedo", "normal")})
    np.testing.assert_array_equal(im.read_reference()["radiance"], layers["radiance"] * 0.5)
    with pytest.raises(FormatError, match="already read"):
        image_from_exr(files + files[:1], tmp_path / "dup")
