"""meta.json and the samples.bin header are covered by checksums (issue 22 items 3 and 4).

meta.json carries ``meta_crc32`` over the rest of itself and records the CRC-32 of the samples.bin
prefix and JSON header; a missing checksum field is an error, never a skip. Each sweep flips bytes
one at a time and requires every flip to be caught or to leave what is read unchanged.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.cli.main import main
from mcdenoise.data.format import ImageMeta, write_image
from mcdenoise.data.meta import seal_meta
from mcdenoise.data.reader import SampleReader
from mcdenoise.data.verify import verify_image
from mcdenoise.errors import FormatError

MASKS = (0x01, 0x40)


def _image(folder: Path, spp: int = 2, h: int = 12, w: int = 14) -> Path:
    rng = np.random.default_rng(0)
    s = {"radiance": (rng.random((spp, 3, h, w)) * 5).astype(np.float32),
         "albedo": rng.random((spp, 3, h, w)).astype(np.float16).astype(np.float32),
         "depth": rng.random((spp, 1, h, w)).astype(np.float32)}
    meta = ImageMeta(width=w, height=h, spp=spp, channels=list(s), scene="s", seed=3,
                     scene_features={"fov": 40.0, "aperture_radius": 0.1}, reference_spp=64)
    return write_image(folder, meta=meta, samples=s, reference={"radiance": s["radiance"].mean(0)})


@pytest.fixture
def img(tmp_path: Path) -> Path:
    return _image(tmp_path / "img")


def _flip(path: Path, offset: int, mask: int = 0x40) -> None:
    raw = bytearray(path.read_bytes())
    raw[offset] ^= mask
    path.write_bytes(bytes(raw))


def test_renamed_checksums_key_does_not_switch_verification_off(img, capfd) -> None:
    """Catches issue 22 item 3's reproduction: `"checksums"` -> `"chebksums"` in meta.json, then
    damaged noisy.exr and samples.bin: `dataset --verify` reported 0 damaged and denoise ran."""
    meta = img / "meta.json"
    meta.write_text(meta.read_text().replace('"checksums"', '"chebksums"'))
    size = (img / "samples.bin").stat().st_size
    _flip(img / "samples.bin", size // 2)
    _flip(img / "noisy.exr", (img / "noisy.exr").stat().st_size // 2)
    assert main(["dataset", "--verify", str(img.parent)]) == 1
    out = capfd.readouterr()
    assert "1 damaged" in out.err and "meta.json" in out.out
    assert main(["denoise", str(img), "-o", str(img.parent / "o.exr"), "--model", "wskp"]) == 1
    assert "meta.json" in capfd.readouterr().err


@pytest.mark.parametrize("drop", ["checksums", "noisy.exr", "reference.exr", "samples_header", "samples_blocks"])
def test_missing_checksum_field_is_an_error(img, drop) -> None:
    """Catches a missing checksum entry being skipped (no verification) instead of refused, even
    when meta.json's own checksum is made to match."""
    doc = json.loads((img / "meta.json").read_text())
    if drop == "checksums":
        del doc["checksums"]
    else:
        del doc["checksums"][drop]
    (img / "meta.json").write_text(json.dumps(seal_meta(doc)))
    problem = verify_image(img)
    assert problem is not None and "meta.json" in problem and "checksum" in problem


def test_meta_json_without_its_own_checksum_is_refused(img) -> None:
    """Catches meta.json lacking meta_crc32 (a damaged key or an unsealed edit) being trusted."""
    doc = json.loads((img / "meta.json").read_text())
    del doc["meta_crc32"]
    (img / "meta.json").write_text(json.dumps(doc))
    problem = verify_image(img)
    assert problem is not None and "meta_crc32" in problem


def test_meta_json_byte_flip_sweep(img) -> None:
    """Catches issue 22 item 3's sweep (1,209 of 2,701 meta.json byte flips missed, scene_features
    among them): every flip of every byte is either reported by `verify_image` or leaves the parsed
    document unchanged."""
    meta = img / "meta.json"
    good = meta.read_bytes()
    want = json.loads(good)
    missed = []
    for i in range(len(good)):
        for mask in MASKS:
            bad = bytearray(good)
            bad[i] ^= mask
            meta.write_bytes(bytes(bad))
            if verify_image(img, full=False) is None:
                try:
                    same = json.loads(bytes(bad)) == want
                except ValueError:
                    same = False
                if not same:
                    missed.append((i, mask))
    meta.write_bytes(good)
    assert verify_image(img) is None
    assert not missed, f"{len(missed)} flips of {len(good)} bytes missed, first {missed[:5]}"


def test_samples_header_byte_flip_sweep(img) -> None:
    """Catches issue 22 item 3's header sweep (489 of 3,016 samples.bin JSON-header byte flips
    missed): every flip in the prefix and header is reported or leaves the parsed header unchanged."""
    path = img / "samples.bin"
    good = path.read_bytes()
    want = SampleReader(path).header
    n = int.from_bytes(good[16:24], "little")
    missed = []
    for i in range(24 + n):
        for mask in MASKS:
            bad = bytearray(good)
            bad[i] ^= mask
            path.write_bytes(bytes(bad))
            if verify_image(img, full=False) is None:
                try:
                    same = SampleReader(path).header == want
                except FormatError:
                    same = False
                if not same:
                    missed.append((i, mask))
    path.write_bytes(good)
    assert not missed, f"{len(missed)} flips missed, first {missed[:5]}"


@pytest.mark.parametrize("byte", [21, 22, 23])
def test_header_length_flip_is_one_line_not_memory_error(img, byte, capfd) -> None:
    """Catches issue 22 item 4: a flipped high byte of the samples.bin header length gave a
    MemoryError traceback in denoise and --verify, and the rest of the scan was lost."""
    other = _image(img.parent / "other")
    _flip(img / "samples.bin", byte, 0x7F)
    with pytest.raises(FormatError, match="header length"):
        SampleReader(img / "samples.bin")  # without meta.json: bounded by the file size alone
    assert main(["dataset", "--verify", str(img.parent)]) == 1
    cap = capfd.readouterr()
    assert "2 image(s) checked, 1 damaged" in cap.err and "Traceback" not in cap.err
    assert str(img / "samples.bin") in cap.out and str(other) not in cap.out
    assert main(["denoise", str(img), "-o", str(img.parent / "o.exr"), "--model", "sbmc"]) == 1
    err = [ln for ln in capfd.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and "samples.bin" in err[0], err
    shutil.rmtree(other)


@pytest.mark.parametrize("edit", ["bad split", "duplicate path"])
def test_verify_checks_the_manifest(tmp_path, capfd, edit) -> None:
    """Catches issue 22 item 10: a manifest.json with a bad split or a path listed twice passed
    `dataset --verify`."""
    from train_tiny_data import make_tiny_dataset

    root = make_tiny_dataset(tmp_path / "data", train=2, val=1, spp=2, size=16)
    doc = json.loads((root / "manifest.json").read_text())
    if edit == "bad split":
        doc["images"][0]["split"] = "trian"
    else:
        doc["images"].append(dict(doc["images"][0]))
    (root / "manifest.json").write_text(json.dumps(doc))
    capfd.readouterr()
    assert main(["dataset", "--verify", str(root)]) == 1
    out = capfd.readouterr().out
    assert "manifest.json" in out and ("trian" in out or "listed twice" in out), out


def test_nonfinite_hint_names_what_a_cli_user_can_do(tmp_path) -> None:
    """Catches issue 22 item 10: the NaN-data hint said "pass sanitize=True", which no command takes."""
    rng = np.random.default_rng(0)
    s = {"radiance": rng.random((2, 3, 8, 8)).astype(np.float32)}
    s["radiance"][0, 0, 1, 1] = np.nan
    folder = write_image(tmp_path / "nan", meta=ImageMeta(width=8, height=8, spp=2, channels=["radiance"]), samples=s)
    from mcdenoise.data.format import read_image

    with pytest.raises(FormatError, match="--nonfinite sanitize"):
        read_image(folder).read_noisy(["radiance"])
