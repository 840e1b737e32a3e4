"""Data format v1: exact round trips, crops that read only what they need, one-line errors."""

from __future__ import annotations

import json
import os
import struct
import warnings
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.data.dataset import Dataset, assign_splits, write_manifest
from mcdenoise.data.format import (
    FORMAT_VERSION,
    ImageMeta,
    SampleReader,
    SampleWriter,
    pixel_stats,
    read_image,
    write_image,
)
from mcdenoise.errors import FormatError
from mcdenoise.io.exr import read_exr_raw, write_exr


def _samples(rng: np.random.Generator, s: int, h: int, w: int) -> dict[str, np.ndarray]:
    """Per-sample buffers whose values survive their storage dtype exactly."""
    return {
        "radiance": (rng.random((s, 3, h, w)) * 20).astype(np.float32),
        # albedo is half_ok -> stored as float16: give it float16-representable values.
        "albedo": rng.random((s, 3, h, w)).astype(np.float16).astype(np.float32),
        "depth": (rng.random((s, 1, h, w)) * 100).astype(np.float32),
    }


def _meta(samples: dict[str, np.ndarray], **kw) -> ImageMeta:
    s, _, h, w = next(iter(samples.values())).shape
    base = dict(channels=list(samples), scene="cornell", seed=7, renderer="test", scene_features={"fov": 39.3, "aperture_radius": 0.0},
                reference_spp=64, extra={"max_depth": 5})
    base.update(kw)
    return ImageMeta(width=w, height=h, spp=s, **base)


def _one_line(err: pytest.ExceptionInfo, path: Path | str) -> str:
    msg = str(err.value)
    assert "\n" not in msg
    assert str(path) in msg, msg
    return msg


@pytest.fixture
def image(tmp_path: Path):
    rng = np.random.default_rng(1)
    smp = _samples(rng, 4, 21, 27)
    ref = {"radiance": rng.random((3, 21, 27)).astype(np.float32), "albedo": rng.random((3, 21, 27)).astype(np.float32)}
    folder = write_image(tmp_path / "img", meta=_meta(smp), samples=smp, reference=ref, tile=8)
    return folder, smp, ref


def test_round_trip_exact(image):
    folder, smp, ref = image
    im = read_image(folder)
    assert im.meta == _meta(smp)
    assert im.samples is not None and im.samples.channels == ["radiance", "albedo", "depth"]
    got = im.samples.read()
    for name, arr in smp.items():
        assert got[name].dtype == np.float32
        np.testing.assert_array_equal(got[name], arr)
    # Storage dtypes follow half_ok.
    dtypes = {e["name"]: e["dtype"] for e in im.samples.header["channels"]}
    assert dtypes == {"radiance": "float32", "albedo": "float16", "depth": "float32"}
    noisy = im.read_noisy()
    assert sorted(noisy) == sorted(list(smp) + [n + "_variance" for n in smp])
    for name, arr in smp.items():
        mean, var = pixel_stats(arr)
        np.testing.assert_allclose(noisy[name], mean, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(noisy[name + "_variance"], var, rtol=1e-5, atol=1e-9)
    got_ref = im.read_reference()
    for name in ref:
        np.testing.assert_array_equal(got_ref[name], ref[name])
    # The raw tiled section is memory-mappable: (tiles_y, tiles_x, spp, C, tile, tile).
    mm = im.samples.memmap("depth")
    assert mm.shape == (3, 4, 4, 1, 8, 8)
    assert mm[1, 2, 3, 0, 4, 5] == smp["depth"][3, 0, 8 + 4, 16 + 5]
    # The header carries the scene features and provenance too.
    assert im.samples.scene_features == {"fov": 39.3, "aperture_radius": 0.0}
    assert im.samples.provenance == {"scene": "cornell", "seed": 7, "renderer": "test"}


def test_pixel_stats_is_variance_of_the_mean():
    x = np.array([1.0, 2.0, 4.0, 5.0], np.float32).reshape(4, 1, 1, 1)
    mean, var = pixel_stats(x)
    assert mean.item() == pytest.approx(3.0)
    # sample variance (1+4+...)/3 = (4+1+1+4)/3 = 10/3; of the mean: /4
    assert var.item() == pytest.approx(10.0 / 3.0 / 4.0)
    assert pixel_stats(x[:1])[1].item() == 0.0


@pytest.mark.parametrize(
    "crop,samples",
    [((0, 0, 21, 27), None), ((3, 5, 7, 9), None), ((8, 8, 8, 8), slice(1, 3)), ((20, 26, 1, 1), [3, 0, 0, 2]),
     ((1, 0, 20, 27), [2])],
)
def test_crop_and_sample_subset(image, crop, samples):
    folder, smp, _ = image
    r = read_image(folder).samples
    y0, x0, h, w = crop
    got = r.read(["depth", "radiance"], crop=crop, samples=samples)
    assert list(got) == ["depth", "radiance"]
    sel = slice(None) if samples is None else samples
    for name in got:
        np.testing.assert_array_equal(got[name], smp[name][sel][:, :, y0 : y0 + h, x0 : x0 + w])
    noisy = read_image(folder).read_noisy(["radiance"], crop=crop)
    assert noisy["radiance"].shape == (3, h, w)


def _rchar() -> int | None:
    try:
        for line in Path("/proc/self/io").read_text().splitlines():
            if line.startswith("rchar:"):
                return int(line.split()[1])
    except OSError:
        return None
    return None


def test_crop_reads_only_needed_bytes(tmp_path: Path):
    """A 32x32 crop of a 256x256, 8 spp image reads 1/64 of the channel; one sample of it 1/512."""
    rng = np.random.default_rng(2)
    s, h, w = 8, 256, 256
    rad = rng.random((s, 3, h, w), dtype=np.float32)
    meta = ImageMeta(width=w, height=h, spp=s, channels=["radiance"])
    folder = write_image(tmp_path / "big", meta=meta, samples={"radiance": rad}, noisy={"radiance": rad[0]})
    reader = SampleReader(folder)
    file_size = (folder / "samples.bin").stat().st_size
    channel_bytes = s * 3 * h * w * 4
    assert file_size >= channel_bytes

    before = _rchar()
    got = reader.read(crop=(64, 96, 32, 32))
    after = _rchar()
    np.testing.assert_array_equal(got["radiance"], rad[:, :, 64:96, 96:128])
    needed = channel_bytes // 64  # exactly one 32x32 tile, all samples
    assert reader.bytes_read == needed
    if before is not None:  # OS-level counter of bytes returned by read syscalls
        assert needed <= after - before < needed + 4096, (after - before, needed)
        assert after - before < file_size / 50

    reader.bytes_read = 0
    before = _rchar()
    got = reader.read(crop=(64, 96, 32, 32), samples=[5])
    after = _rchar()
    np.testing.assert_array_equal(got["radiance"], rad[5:6, :, 64:96, 96:128])
    assert reader.bytes_read == needed // s
    if before is not None:
        assert needed // s <= after - before < needed // s + 4096

    # An unaligned 40x40 crop overlaps 2x3 tiles: 6/64 of the channel.
    reader.bytes_read = 0
    reader.read(crop=(60, 70, 40, 40))
    assert reader.bytes_read == 6 * needed


def test_streaming_writer_matches_write_image(tmp_path: Path, image):
    folder, smp, ref = image
    meta = _meta(smp)
    w = SampleWriter(tmp_path / "streamed", meta, tile=8)
    assert not (tmp_path / "streamed").exists()  # nothing visible before finish()
    # Out of order: sample blocks x row bands that do not align with tiles.
    for s0, s1 in ((2, 4), (0, 2)):
        for y0, y1 in ((13, 21), (0, 5), (5, 13)):
            for name, arr in smp.items():
                w.write(name, arr[s0:s1, :, y0:y1], samples=slice(s0, s1), rows=slice(y0, y1))
    out = w.finish(reference=ref)
    a, b = read_image(out), read_image(folder)
    for name in smp:
        np.testing.assert_array_equal(a.samples.read([name])[name], smp[name])
    na, nb = a.read_noisy(), b.read_noisy()
    for name in na:
        np.testing.assert_allclose(na[name], nb[name], rtol=1e-5, atol=1e-9)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_writer_validates_and_stays_atomic(tmp_path: Path, image):
    folder, smp, ref = image
    with pytest.raises(FileExistsError):
        write_image(folder, meta=_meta(smp), samples=smp)
    bad = dict(smp, depth=smp["depth"][:, :, :-1])
    with pytest.raises(ValueError, match="depth"):
        write_image(tmp_path / "bad", meta=_meta(smp), samples=bad)
    with pytest.raises(ValueError, match="float16"):
        write_image(tmp_path / "bad", meta=_meta(smp), samples=smp, half=["radiance"])
    with pytest.raises(FormatError, match="not in the channel vocabulary"):
        write_image(tmp_path / "bad", meta=_meta(smp, channels=["radiance", "bogus"]), samples=smp)
    with pytest.raises(FormatError, match="unknown scene feature"):
        write_image(tmp_path / "bad", meta=_meta(smp, scene_features={"zoom": 1.0}), samples=smp)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img"]  # no temp leftovers
    # overwrite replaces the folder in one rename.
    smp2 = {k: v[:2] for k, v in smp.items()}
    write_image(folder, meta=_meta(smp2), samples=smp2, overwrite=True)
    assert read_image(folder).meta.spp == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img"]


def test_pixel_only_image(tmp_path: Path):
    rng = np.random.default_rng(3)
    noisy = {"radiance": rng.random((3, 5, 6)).astype(np.float32),
             "radiance_variance": rng.random((3, 5, 6)).astype(np.float32)}
    meta = ImageMeta(width=6, height=5, spp=16, channels=["radiance"])
    im = read_image(write_image(tmp_path / "px", meta=meta, noisy=noisy))
    assert im.samples is None and not im.has_reference and im.read_reference() is None
    got = im.read_noisy()
    for k in noisy:
        np.testing.assert_array_equal(got[k], noisy[k])


# ----------------------------------------------------------------------------- errors


def test_wrong_version(image):
    folder, _, _ = image
    meta_path = folder / "meta.json"
    doc = json.loads(meta_path.read_text())
    doc["version"] = FORMAT_VERSION + 1
    meta_path.write_text(json.dumps(doc))
    with pytest.raises(FormatError) as err:
        read_image(folder)
    assert "version 2" in _one_line(err, meta_path)

    samples = folder / "samples.bin"
    data = bytearray(samples.read_bytes())
    data[8:12] = struct.pack("<I", 9)
    samples.write_bytes(bytes(data))
    with pytest.raises(FormatError) as err:
        SampleReader(samples)
    assert "version 9" in _one_line(err, samples)


def test_truncated_and_corrupt_samples(image):
    folder, _, _ = image
    samples = folder / "samples.bin"
    data = samples.read_bytes()
    samples.write_bytes(data[: len(data) - 100])
    with pytest.raises(FormatError) as err:
        read_image(folder)
    assert "truncated" in _one_line(err, samples)
    samples.write_bytes(data[:20])
    with pytest.raises(FormatError) as err:
        SampleReader(samples)
    assert "truncated" in _one_line(err, samples)
    samples.write_bytes(b"NOTMAGIC" + data[8:])
    with pytest.raises(FormatError) as err:
        SampleReader(samples)
    assert "not an mcdenoise samples file" in _one_line(err, samples)
    samples.write_bytes(data[:24] + b"#" + data[25:])
    with pytest.raises(FormatError) as err:
        SampleReader(samples)
    assert "corrupt JSON header" in _one_line(err, samples)
    samples.write_bytes(data.replace(b'"dtype": "float32"', b'"dtypX": "float32"', 1))
    with pytest.raises(FormatError) as err:
        SampleReader(samples)
    assert "corrupt header" in _one_line(err, samples)
    samples.write_bytes(data.replace(b'"dtype": "float32"', b'"dtype": "float64"', 1))
    with pytest.raises(FormatError) as err:
        SampleReader(samples)
    assert "unsupported dtype 'float64'" in _one_line(err, samples)


def test_missing_channel_and_shape_mismatch(image):
    folder, smp, _ = image
    im = read_image(folder)
    with pytest.raises(FormatError) as err:
        im.samples.read(["normal"])
    assert "missing channel 'normal'" in _one_line(err, folder / "samples.bin")
    with pytest.raises(FormatError) as err:
        im.read_noisy(["normal_variance"])
    assert "missing channel" in _one_line(err, folder / "noisy.exr")
    # A noisy.exr of the wrong size.
    write_exr(folder / "noisy.exr", {"radiance": np.zeros((3, 4, 4), np.float32)})
    with pytest.raises(FormatError) as err:
        read_image(folder).read_noisy()
    assert "shape mismatch" in _one_line(err, folder / "noisy.exr")


def test_truncated_noisy_exr(image):
    folder, _, _ = image
    p = folder / "noisy.exr"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError) as err:
        read_image(folder).read_noisy()
    assert "truncated or corrupt" in _one_line(err, p)


def test_nan_inf_reported_and_sanitised(tmp_path: Path):
    rng = np.random.default_rng(4)
    smp = _samples(rng, 3, 10, 12)
    smp["radiance"][1, 2, 4, 7] = np.nan
    smp["radiance"][2, 0, 9, 11] = np.inf
    folder = write_image(tmp_path / "nan", meta=_meta(smp), samples=smp, tile=8)
    r = read_image(folder).samples
    with pytest.raises(FormatError) as err:
        r.read(["radiance"])
    msg = _one_line(err, folder / "samples.bin")
    assert "2 non-finite value(s) (1 NaN, 1 Inf)" in msg
    assert "sample 1, component B, pixel (y=4, x=7)" in msg
    # Locations are reported in image coordinates, also for crops.
    with pytest.raises(FormatError, match=r"pixel \(y=9, x=11\)"):
        r.read(["radiance"], crop=(8, 8, 2, 4))
    r.read(["albedo", "depth"])  # other channels are clean
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = r.read(["radiance"], sanitize=True)["radiance"]
    assert any("non-finite" in str(w.message) for w in caught)
    assert np.isfinite(got).all() and got[1, 2, 4, 7] == 0 and got[2, 0, 9, 11] == 0
    clean = smp["radiance"].copy()
    clean[~np.isfinite(clean)] = 0
    np.testing.assert_array_equal(got, clean)
    # The noisy means inherit the NaN: the pixel reader reports it too.
    with pytest.raises(FormatError, match="non-finite"):
        read_image(folder).read_noisy(["radiance"])


def test_noisy_exr_opens_as_plain_multilayer_exr(image):
    folder, _, _ = image
    names = set(read_exr_raw(folder / "noisy.exr"))
    assert {"radiance.R", "radiance_variance.B", "depth.Y", "albedo_variance.G"} <= names


# ----------------------------------------------------------------------------- dataset


def test_assign_splits_deterministic_and_disjoint():
    scenes = [f"scene{i:02d}" for i in range(20)]
    a = assign_splits(scenes, seed=3)
    assert a == assign_splits(list(reversed(scenes)) + scenes[:3], seed=3)
    counts = {s: sum(v == s for v in a.values()) for s in ("train", "val", "test")}
    assert counts == {"train": 16, "val": 2, "test": 2}
    assert a != assign_splits(scenes, seed=4)
    small = assign_splits(["a", "b", "c"])
    assert sorted(small.values()) == ["test", "train", "val"]
    assert set(assign_splits(["a", "b"], fractions=(1, 0, 0)).values()) == {"train"}


def test_manifest_and_dataset(tmp_path: Path):
    rng = np.random.default_rng(5)
    entries = []
    for scene, split in (("a", "train"), ("a", "train"), ("b", "test")):
        rel = f"{scene}/{len(entries)}"
        meta = ImageMeta(width=4, height=3, spp=2, channels=["radiance"], scene=scene)
        write_image(tmp_path / rel, meta=meta, noisy={"radiance": rng.random((3, 3, 4)).astype(np.float32)})
        entries.append({"path": rel, "scene": scene, "split": split})
    with pytest.raises(FormatError, match="scene 'a' is in two splits"):
        write_manifest(tmp_path, entries + [dict(entries[1], split="val", path="a/x")])
    write_manifest(tmp_path, entries)
    ds = Dataset(tmp_path)
    assert len(ds) == 3 and ds.scenes("train") == ["a"] and ds.scenes("test") == ["b"]
    assert [im.meta.scene for im in ds.images("train")] == ["a", "a"]
    assert ds.images("val") == []
    # A manifest edited by hand into an invalid state is refused with a one-line error.
    m = tmp_path / "manifest.json"
    doc = json.loads(m.read_text())
    doc["images"][2]["scene"] = "a"
    m.write_text(json.dumps(doc))
    with pytest.raises(FormatError) as err:
        Dataset(tmp_path)
    assert "two splits" in _one_line(err, m)
    doc["images"][2]["scene"] = "b"
    doc["images"][2]["path"] = "missing/0"
    m.write_text(json.dumps(doc))
    with pytest.raises(FormatError, match="no such file"):
        Dataset(tmp_path)
    os.remove(m)
    with pytest.raises(FormatError, match="no such file"):
        Dataset(tmp_path)


# ----------------------------------------------------------------------------- crop sampler


def test_crop_sampler(image):
    from mcdenoise.data.sampler import CropSampler

    folder, smp, ref = image
    im = read_image(folder)
    s = CropSampler([im], crop=8, channels=["radiance", "depth"], spp_range=(2, 3), seed=5)
    a, b = s[3], s[3]
    assert a.origin == b.origin and a.samples == b.samples  # a pure function of (seed, i)
    assert any(s[i].origin != a.origin for i in range(4, 10))
    y0, x0 = a.origin
    assert len(a.samples) in (2, 3) and a.samples == sorted(set(a.samples))
    np.testing.assert_array_equal(a.inputs["radiance"], smp["radiance"][a.samples][:, :, y0 : y0 + 8, x0 : x0 + 8])
    np.testing.assert_array_equal(a.reference["radiance"], ref["radiance"][:, y0 : y0 + 8, x0 : x0 + 8])
    assert a.scene_features.shape == (5,) and a.scene_features[0] == np.float32(39.3)

    # Pixel inputs from a sample subset are recomputed from exactly that subset.
    p = CropSampler([im], crop=8, channels=["radiance", "radiance_variance"], kind="pixels", spp_range=(2, 2))
    c = p[0]
    y0, x0 = c.origin
    mean, var = pixel_stats(smp["radiance"][c.samples][:, :, y0 : y0 + 8, x0 : x0 + 8])
    np.testing.assert_array_equal(c.inputs["radiance"], mean)
    np.testing.assert_array_equal(c.inputs["radiance_variance"], var)
    # Without spp_range the stored noisy.exr is used.
    d = CropSampler([im], crop=8, channels=["albedo_variance"], kind="pixels")[1]
    y0, x0 = d.origin
    np.testing.assert_allclose(d.inputs["albedo_variance"], im.read_noisy(["albedo_variance"])["albedo_variance"][:, y0 : y0 + 8, x0 : x0 + 8])

    with pytest.raises(ValueError, match="smaller than"):
        CropSampler([im], crop=22, channels=["radiance"])
    with pytest.raises(ValueError, match="spp_range"):
        CropSampler([im], crop=8, channels=["radiance"], spp_range=(1, 9))


def test_writer_abort_and_extra_noisy(tmp_path: Path, image):
    _, smp, _ = image
    meta = _meta(smp)
    with pytest.raises(KeyError):
        with SampleWriter(tmp_path / "aborted", meta, tile=8) as w:
            w.write("radiance", smp["radiance"])
            w.write("normal", smp["radiance"])  # not in meta.channels
    assert list(tmp_path.iterdir()) == [tmp_path / "img"]  # no folder, no temp leftovers
    w = SampleWriter(tmp_path / "extra", meta, tile=8)
    for name, arr in smp.items():
        w.write(name, arr)
    pos = np.arange(3 * 21 * 27, dtype=np.float32).reshape(3, 21, 27)
    noisy = w.noisy_from_samples()
    out = w.finish(extra_noisy={"position": pos})
    got = read_image(out).read_noisy()
    np.testing.assert_array_equal(got["position"], pos)
    np.testing.assert_array_equal(got["radiance"], noisy["radiance"])
    # A noisy.exr lacking a channel meta.json lists is refused on read.
    write_exr(out / "noisy.exr", {"radiance": pos})
    with pytest.raises(FormatError, match="missing channel 'albedo' listed in meta.json"):
        read_image(out).read_noisy(["radiance"])
