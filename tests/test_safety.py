"""Issue 13: nothing lost, nothing silent. Each test is one reproduction from the issue: exit code 1
(or the library's error), one line naming the path and the problem, no traceback, nothing of the
user's deleted, no temporary folders left behind."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.cli.main import main
from mcdenoise.data.finite import sanitize_nonfinite
from mcdenoise.data.format import ImageMeta, read_image, write_image
from mcdenoise.data.verify import verify_image
from mcdenoise.errors import FormatError, NonFiniteError, OutputError
from mcdenoise.io import safety
from mcdenoise.io.safety import WriterLock, atomic_dir, check_space, remove_stale_temps, temp_sibling


def _image(folder: Path, spp: int = 4, h: int = 40, w: int = 50, **kw) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    s = {"radiance": (rng.random((spp, 3, h, w)) * 5).astype(np.float32),
         "depth": rng.random((spp, 1, h, w)).astype(np.float32)}
    write_image(folder, meta=ImageMeta(width=w, height=h, spp=spp, channels=list(s)), samples=s,
                reference={"radiance": s["radiance"].mean(0)}, **kw)
    return s


def _no_temps(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if ".tmp-" in p.name or ".old-" in p.name]


@contextlib.contextmanager
def _tmpfs(mnt: Path, options: str) -> Iterator[Path]:
    """A small tmpfs mounted at ``mnt`` for the block (skips the test where mounting is not allowed)."""
    mnt.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mnt)], capture_output=True).returncode:
        pytest.skip(f"cannot mount a tmpfs ({options}) here (not root?)")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=False)


def _one_error_line(capsys: pytest.CaptureFixture, *needles: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    err = [ln for ln in err if "Warning" not in ln and not ln.startswith("  warnings.warn")]
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    for n in needles:
        assert n in err[0], (n, err[0])
    return err[0]


# ----------------------------------------------------------------------------- 1. overwrite


def test_overwrite_refuses_a_folder_mcdenoise_did_not_write(tmp_path: Path) -> None:
    """Bug: --overwrite deleted precious/t.txt (any folder, or a plain file, was replaced)."""
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "t.txt").write_text("x")
    with pytest.raises(OutputError, match="replaces only mcdenoise output"):
        _image(precious, overwrite=True)
    assert (precious / "t.txt").read_text() == "x"
    plain = tmp_path / "plain"
    plain.write_text("y")
    with pytest.raises(OutputError, match="plain file"):
        _image(plain, overwrite=True)
    assert plain.read_text() == "y"
    assert _no_temps(tmp_path) == []


def test_overwrite_replaces_an_mcdenoise_image(tmp_path: Path) -> None:
    """Bug it would catch: the recognition refusing our own image folders (--overwrite useless)."""
    _image(tmp_path / "img")
    _image(tmp_path / "img", spp=2, overwrite=True)
    assert read_image(tmp_path / "img").meta.spp == 2
    assert _no_temps(tmp_path) == []


# ----------------------------------------------------------------------------- 2. size and space


def test_space_check_refuses_before_allocating(tmp_path: Path) -> None:
    """Bug: a 249 GB sparse samples.bin was created on a 78 GB disk; now refused up front."""
    with pytest.raises(OutputError, match="cap"):
        check_space(tmp_path / "x", 10**12, max_bytes=10**9)
    free = __import__("shutil").disk_usage(tmp_path).free
    with pytest.raises(OutputError, match="free there"):
        check_space(tmp_path / "x", free * 2, max_bytes=None)
    with pytest.raises(OutputError, match="cap"):
        _image(tmp_path / "big", max_bytes=1000)
    assert list(tmp_path.iterdir()) == []


def test_disk_full_while_allocating_is_one_line_and_leaves_no_temp(tmp_path: Path, monkeypatch) -> None:
    """Bug: a disk filling during the write ended in a Bus error (SIGBUS on the sparse memmap)
    and a hidden .tmp folder. ENOSPC is simulated here (see the tmpfs test for a real one)."""
    def full(fd: int, off: int, n: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    with pytest.raises(OutputError, match="the disk is full"):
        _image(tmp_path / "img")
    assert list(tmp_path.iterdir()) == []


def test_disk_full_on_a_real_tmpfs(tmp_path: Path, monkeypatch) -> None:
    """The same on a real 2 MB tmpfs (space pre-check bypassed so the write itself fills it)."""
    with _tmpfs(tmp_path / "small", "size=2m") as mnt:
        monkeypatch.setattr("mcdenoise.data.writer.check_space", lambda *a, **k: None)
        with pytest.raises(OutputError, match="the disk is full"):
            _image(mnt / "img", spp=64, h=128, w=128)
        assert list(mnt.iterdir()) == []


def test_stale_temp_of_a_killed_writer_is_removed(tmp_path: Path) -> None:
    """Bug: .x.tmp-* folders of killed runs stayed forever; a live writer's must stay."""
    final = tmp_path / "img"
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = temp_sibling(final).name.replace(f"-{os.getpid()}-", f"-{dead.pid}-")
    (tmp_path / stale).mkdir()
    live = temp_sibling(final)  # our own pid: alive
    live.mkdir()
    assert remove_stale_temps(final) == [tmp_path / stale]
    assert live.exists()
    live.rmdir()
    (tmp_path / stale).mkdir()
    _image(final)
    assert _no_temps(tmp_path) == []


# ----------------------------------------------------------------------------- 3. locks


def test_second_writer_is_refused_and_stale_lock_taken_over(tmp_path: Path) -> None:
    """Bug: two dataset runs into one folder deleted each other's images; now the second is refused."""
    lock = WriterLock(tmp_path / ".lock", "first").acquire()
    with pytest.raises(OutputError, match="another mcdenoise run is writing here"):
        WriterLock(tmp_path / ".lock", "second").acquire()
    lock.release()
    dead = subprocess.Popen(["true"])
    dead.wait()
    (tmp_path / ".lock").write_text(json.dumps({"pid": dead.pid, "host": safety._HOST, "what": "killed"}))
    with WriterLock(tmp_path / ".lock", "third"):
        assert json.loads((tmp_path / ".lock").read_text())["pid"] == os.getpid()
    assert not (tmp_path / ".lock").exists()


def test_dataset_shard_locks_overlap_only_when_indices_do() -> None:
    """Bug it would catch: disjoint shards (0/2 and 1/2) refusing each other, or 0/1 and 1/2 not."""
    from mcdenoise.render.procedural_dataset import _shards_overlap

    assert not _shards_overlap({"what": "shard 1/2"}, 0, 2)
    assert _shards_overlap({"what": "shard 1/2"}, 0, 1)
    assert _shards_overlap({"what": "shard 0/2"}, 2, 4)
    assert not _shards_overlap({"what": "shard 1/2"}, 2, 4)


# ----------------------------------------------------------------------------- 4. integrity


def test_byte_flip_is_found_on_read_and_by_verify(tmp_path: Path, capsys) -> None:
    """Bug: a one-byte flip inside samples.bin read back silently as wrong values."""
    _image(tmp_path / "ds" / "a")
    _image(tmp_path / "ds" / "b")
    assert main(["dataset", "--verify", str(tmp_path / "ds")]) == 0
    img = read_image(tmp_path / "ds" / "b")
    off = img.samples._entries["depth"]["offset"] + 123
    with open(img.samples.path, "r+b") as f:
        f.seek(off)
        b = f.read(1)
        f.seek(off)
        f.write(bytes([b[0] ^ 0x10]))
    with pytest.raises(FormatError, match="checksum mismatch in channel 'depth'"):
        read_image(tmp_path / "ds" / "b").samples.read(["depth"])
    capsys.readouterr()
    assert main(["dataset", "--verify", str(tmp_path / "ds")]) == 1
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "ds/b/samples.bin: damaged" in out[0]


def test_truncated_samples_is_not_finished(tmp_path: Path) -> None:
    """Bug: a truncated samples.bin was counted as done by a rerun / --merge."""
    _image(tmp_path / "img")
    p = tmp_path / "img" / "samples.bin"
    p.write_bytes(p.read_bytes()[:-4])
    assert "truncated" in (verify_image(tmp_path / "img", full=False) or "")
    from mcdenoise.render.procedural_dataset import _is_finished

    assert not _is_finished(tmp_path / "img")


def test_damaged_exr_is_found(tmp_path: Path) -> None:
    """Bug it would catch: checksums covering samples.bin only, not noisy/reference EXRs."""
    _image(tmp_path / "img")
    p = tmp_path / "img" / "reference.exr"
    data = bytearray(p.read_bytes())
    data[-10] ^= 1
    p.write_bytes(bytes(data))
    assert "reference.exr: damaged" in (verify_image(tmp_path / "img") or "")


# ----------------------------------------------------------------------------- 5. non-finite


def test_nonfinite_rule_sanitize_and_error(tmp_path: Path) -> None:
    """Bug: NaN/Inf samples were written with exit 0 into a folder our reader then refuses."""
    a = np.array([1.0, np.nan, np.inf, -np.inf], np.float32)
    out, n = sanitize_nonfinite(a, "sanitize", "x")
    assert n == 3 and out.tolist() == [1.0, 0.0, 0.0, 0.0] and np.isnan(a[1])
    with pytest.raises(NonFiniteError, match="3 non-finite"):
        sanitize_nonfinite(a, "error", "x")
    s = {"radiance": np.full((2, 3, 8, 8), np.nan, np.float32)}
    from mcdenoise.data.writer import SampleWriter

    w = SampleWriter(tmp_path / "img", ImageMeta(width=8, height=8, spp=2, channels=["radiance"]), nonfinite="sanitize")
    w.write("radiance", s["radiance"])
    w.finish()
    img = read_image(tmp_path / "img")
    assert img.meta.extra["nonfinite_replaced"] == 2 * 3 * 64
    assert np.all(img.samples.read()["radiance"] == 0)
    w = SampleWriter(tmp_path / "img2", ImageMeta(width=8, height=8, spp=2, channels=["radiance"]), nonfinite="error")
    with pytest.raises(NonFiniteError):
        w.write("radiance", s["radiance"])
    w.abort()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["img"]


# ----------------------------------------------------------------------------- 6/7. CLI one-liners


@pytest.mark.parametrize("out, needle", [
    (".", "current folder"),
    ("", "current folder"),
    ("plainfile/sub", "is a plain file"),
])
def test_render_bad_out_is_one_line(tmp_path: Path, monkeypatch, capsys, out: str, needle: str) -> None:
    """Bug: --out . / "" / under a plain file ended in a traceback or replaced the working folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plainfile").write_text("z")
    (tmp_path / "keep.txt").write_text("k")
    assert main(["render", "cornell-box", "--spp", "1", "--ref-spp", "0", "--size", "16", "--out", out,
                 "--overwrite"]) == 1
    _one_error_line(capsys, needle)
    assert (tmp_path / "keep.txt").exists() and (tmp_path / "plainfile").read_text() == "z"


def test_render_non_utf8_out_is_one_line(tmp_path: Path, capsys) -> None:
    """Bug: a non-UTF-8 --out crashed with UnicodeEncodeError."""
    bad = os.fsdecode(os.fsencode(str(tmp_path)) + b"/caf\xe9")
    assert main(["render", "cornell-box", "--spp", "1", "--ref-spp", "0", "--size", "16", "--out", bad]) == 1
    _one_error_line(capsys, "not valid UTF-8")


def test_render_precious_folder_and_huge_size(tmp_path: Path, capsys) -> None:
    """Bugs: --overwrite deleted precious/t.txt; --size 16384 made a 249 GB sparse file."""
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "t.txt").write_text("x")
    assert main(["render", "cornell-box", "--spp", "1", "--ref-spp", "0", "--size", "16", "--out", str(precious),
                 "--overwrite"]) == 1
    _one_error_line(capsys, str(precious), "replaces only mcdenoise output")
    assert (precious / "t.txt").read_text() == "x"
    assert main(["render", "cornell-box", "--spp", "8", "--ref-spp", "0", "--size", "16384",
                 "--out", str(tmp_path / "huge")]) == 1
    _one_error_line(capsys, "huge", "GB")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious"]


def test_dataset_bad_split_and_seed_are_refused_before_writing(tmp_path: Path, capsys) -> None:
    """Bugs: --split nan,0,0 wrote NaN into dataset.json; a seed above 32 bits equalled seed 0."""
    for split in ("nan,0,0", "inf,0,0"):
        assert main(["dataset", "--count", "1", "--out", str(tmp_path / "d"), "--split", split]) == 1
        _one_error_line(capsys, "--split")
    assert main(["dataset", "--count", "1", "--out", str(tmp_path / "d"), "--seed", str(2**32)]) == 1
    _one_error_line(capsys, "32-bit")
    assert not (tmp_path / "d").exists()


def test_debug_flag_shows_the_traceback(tmp_path: Path) -> None:
    """Bug it would catch: --debug swallowed like the one-line path (no way to get the traceback)."""
    with pytest.raises(OutputError):
        main(["--debug", "render", "cornell-box", "--size", "16", "--ref-spp", "0", "--out", "."])


def test_meta_json_with_null_fields_is_one_line(tmp_path: Path) -> None:
    """Bug: meta.json with null fields (channels, scene_features...) raised TypeError. (Sealed with a
    matching meta_crc32, so the field checks behind the checksum are what is tested.)"""
    from mcdenoise.data.meta import seal_meta

    _image(tmp_path / "img")
    meta = tmp_path / "img" / "meta.json"
    doc = json.loads(meta.read_text())
    for key in ("channels", "width", "scene_features", "seed"):
        meta.write_text(json.dumps(seal_meta({**doc, key: None})))
        with pytest.raises(FormatError, match=key):
            read_image(tmp_path / "img")


def test_read_only_output_is_one_line(tmp_path: Path, capsys) -> None:
    """Bug: a read-only output place ended in a PermissionError/OSError traceback."""
    with _tmpfs(tmp_path / "ro", "size=1m,ro") as mnt:
        assert main(["render", "cornell-box", "--spp", "1", "--ref-spp", "0", "--size", "16",
                     "--out", str(mnt / "img")]) == 1
        _one_error_line(capsys, str(mnt), "read-only")


def test_concurrent_render_into_one_output_is_refused(tmp_path: Path, capsys) -> None:
    """Bug: two renders into one --out raced on the temporary and the rename."""
    with WriterLock(tmp_path / ".img.lock", "render img"):
        assert main(["render", "cornell-box", "--spp", "1", "--ref-spp", "0", "--size", "16",
                     "--out", str(tmp_path / "img")]) == 1
    _one_error_line(capsys, str(tmp_path), "another mcdenoise run is writing here")
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_repro_and_demo_bad_arguments_are_one_line(tmp_path: Path, capsys) -> None:
    """Bugs: `repro --out` naming a plain file ended in a traceback; `demo --size 5` rendered a
    useless 5x5 image (issue 13 item 6)."""
    plain = tmp_path / "plain"
    plain.write_text("x")
    assert main(["repro", "wskp-fig9", "--out", str(plain), "--steps", "1", "--quiet"]) == 1
    _one_error_line(capsys, str(plain), "plain file")
    assert plain.read_text() == "x"
    assert main(["demo", "--size", "5", "--out", str(tmp_path / "d")]) == 1
    _one_error_line(capsys, "--size 5")
    assert not (tmp_path / "d").exists()
