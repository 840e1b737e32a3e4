"""`mcdenoise dataset`: splits, determinism across shards, resume after a kill, merge, sequences."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.cli.main import main
from mcdenoise.data.dataset import Dataset, read_manifest
from mcdenoise.data.format import read_image
from mcdenoise.render.procedural import derive_seed
from mcdenoise.render.procedural_dataset import shard_indices

pytestmark = pytest.mark.render

# Tiny but real: 16x16, 2 spp, reference 16 spp, few objects (JIT time grows with objects).
TINY = ["--spp", "2", "--ref-spp", "16", "--size", "16", "--objects", "10-12", "--seed", "4", "--no-progress"]


def _run(*args: str) -> int:
    return main(["dataset", *args])


def _radiance(folder: Path) -> np.ndarray:
    return read_image(folder).read_noisy(["radiance"])["radiance"]


@pytest.fixture(scope="module")
def ds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("ds") / "data"
    assert _run("--count", "3", "--out", str(root), *TINY) == 0
    return root


def test_dataset_valid_split(ds: Path) -> None:
    d = Dataset(ds)
    assert len(d) == 3
    entries = read_manifest(ds)
    assert [e["path"] for e in entries] == ["proc_000000", "proc_000001", "proc_000002"]
    # Three scenes: one per split, each scene in exactly one split.
    assert sorted(e["split"] for e in entries) == ["test", "train", "val"]
    for split in ("train", "val", "test"):
        assert len(d.scenes(split)) == 1
    for i, img in enumerate(d.images()):
        assert img.meta.scene == f"proc_{i:06d}"
        proc = img.meta.extra["procedural"]
        assert proc["seed"] == derive_seed(4, i) and proc["index"] == i
        assert proc["kind"] in ("indoor", "outdoor")
        rad = img.read_noisy(["radiance"])["radiance"]
        ref = img.read_reference(["radiance"])["radiance"]
        assert rad.shape == (3, 16, 16) and np.isfinite(rad).all() and rad.mean() > 0
        assert np.isfinite(ref).all() and ref.mean() > 0
        assert img.samples is not None and img.samples.spp == 2


def test_variant_is_recorded(ds: Path) -> None:
    """Catches issue 18: the Mitsuba variant a dataset was rendered with was recorded neither in
    dataset.json nor in the manifest (whose hash names a run's data), so a GPU host's re-render
    passed for the same data."""
    from mcdenoise.data.dataset import read_manifest_settings
    from mcdenoise.render._mitsuba import process_variant

    variant = json.loads((ds / "dataset.json").read_text())["variant"]
    assert variant == process_variant() and variant in read_image(ds / "proc_000000").meta.renderer
    settings = read_manifest_settings(ds)
    assert settings is not None and settings["variant"] == variant and settings["spp"] == 2


def test_shards_are_disjoint_and_cover() -> None:
    parts = [set(shard_indices(10, i, 3)) for i in range(3)]
    assert set().union(*parts) == set(range(10))
    assert sum(len(p) for p in parts) == 10
    assert parts[1] == {1, 4, 7}


def test_shard_renders_same_image_and_merges_by_copying(ds: Path, tmp_path: Path) -> None:
    shard = tmp_path / "shard1"
    assert _run("--count", "3", "--out", str(shard), "--shard", "1/3", *TINY) == 0
    assert sorted(p.name for p in shard.iterdir() if p.name.startswith("proc_")) == ["proc_000001"]
    # Another machine's shard renders the very same pixels for image 1.
    np.testing.assert_array_equal(_radiance(shard / "proc_000001"), _radiance(ds / "proc_000001"))
    # Merge: copy the other shards' folders in, rebuild the manifest.
    for name in ("proc_000000", "proc_000002"):
        shutil.copytree(ds / name, shard / name)
    assert _run("--merge", "--out", str(shard)) == 0
    assert read_manifest(shard) == read_manifest(ds)


def test_only_split_renders_the_full_runs_images_and_resumes_to_it(ds: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """Catches: --only-split rendering other pixels than a full run (a held-out set re-created on a
    new machine would then not be the one the campaign scored), rendering the wrong scenes, or
    leaving a folder that a plain rerun cannot complete into the full recipe's dataset."""
    root = tmp_path / "val_first"
    val = [e["path"] for e in read_manifest(ds) if e["split"] == "val"]
    assert _run("--count", "3", "--out", str(root), "--only-split", "val", *TINY) == 0
    assert [e["path"] for e in read_manifest(root)] == val
    assert sorted(p.name for p in root.iterdir() if p.name.startswith("proc_")) == val
    np.testing.assert_array_equal(_radiance(root / val[0]), _radiance(ds / val[0]))
    assert [img.meta.scene for img in Dataset(root).images("val")] == val
    capsys.readouterr()
    assert _run("--count", "3", "--out", str(root), *TINY) == 0
    assert "rendered 2 image(s)" in capsys.readouterr().out
    assert read_manifest(root) == read_manifest(ds)
    assert _run("--count", "3", "--out", str(tmp_path / "bad"), "--only-split", "valid", *TINY) == 1
    err = capsys.readouterr().err
    assert "--only-split" in err and "valid" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "bad").exists()


def test_resume_after_kill(ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "resume"
    shutil.copytree(ds, root)
    # Simulated kill while image 1 was being written: its folder never got renamed into place and
    # a half-written temporary folder is left behind.
    shutil.rmtree(root / "proc_000001")
    junk = root / ".proc_000001.tmp-999-deadbeef"
    junk.mkdir()
    (junk / "samples.bin").write_bytes(b"MCDSAMPL half written")
    before = (root / "proc_000000" / "meta.json").stat()
    other = root / "proc_000000" / "noisy.exr"
    other_mtime = other.stat().st_mtime_ns
    time.sleep(0.01)
    capsys.readouterr()
    assert _run("--count", "3", "--out", str(root), *TINY) == 0
    out = capsys.readouterr()
    assert "rendered 1 image(s)" in out.out and "2 already done" in out.out
    assert "removed 1 partial leftover" in out.err
    assert not junk.exists()
    after = (root / "proc_000000" / "meta.json").stat()
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)  # not re-rendered
    assert other.stat().st_mtime_ns == other_mtime
    np.testing.assert_array_equal(_radiance(root / "proc_000001"), _radiance(ds / "proc_000001"))
    assert read_manifest(root) == read_manifest(ds)
    # A run with nothing left to do renders nothing.
    assert _run("--count", "3", "--out", str(root), *TINY) == 0
    assert "rendered 0 image(s)" in capsys.readouterr().out


def test_other_options_are_refused(ds: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    args = [a if a != "2" else "4" for a in TINY]  # --spp 4
    assert _run("--count", "3", "--out", str(ds), *args) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "dataset.json" in err and "spp" in err
    assert _run("--count", "3", "--out", str(ds), "--shard", "3/3") == 1
    assert "--shard" in capsys.readouterr().err
    assert _run("--out", str(ds)) == 1
    assert "--count" in capsys.readouterr().err
    for bad, word in ((["--size", "0"], "--size"), (["--size", "99999"], "--size"), (["--objects", "9-3"], "--objects"),
                      (["--frames", "0"], "frames"), (["--split", "1,2"], "--split"), (["--shard", "x"], "--shard")):
        assert _run("--count", "3", "--out", str(ds / "never"), *bad) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and word in err, err
    assert not (ds / "never").exists()  # nothing is created when the options are wrong


def test_merge_without_dataset_is_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run("--merge", "--out", str(tmp_path)) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "dataset.json" in err


def test_sequence_frames_have_consistent_motion(tmp_path: Path) -> None:
    from mcdenoise.render.sequence import project

    root = tmp_path / "seq"
    assert _run("--count", "1", "--frames", "2", "--out", str(root), *TINY) == 0
    entries = read_manifest(root)
    assert [e["path"] for e in entries] == ["proc_000000/frame_000", "proc_000000/frame_001"]
    assert len({e["split"] for e in entries}) == 1 and [e["frame"] for e in entries] == [0, 1]
    f0, f1 = read_image(root / entries[0]["path"]), read_image(root / entries[1]["path"])
    n0 = f0.read_noisy(["motion", "position"])
    np.testing.assert_array_equal(n0["motion"], 0.0)  # first frame: no history
    n1 = f1.read_noisy(["motion", "position"])
    cur = np.asarray(f1.meta.extra["camera_to_world"])
    prev = np.asarray(f1.meta.extra["camera_to_world_prev"])
    assert not np.allclose(cur, prev)  # the camera does move
    np.testing.assert_allclose(prev, np.asarray(f0.meta.extra["camera_to_world"]))
    # Current pixel minus motion = where the pixel's world position projects in the previous
    # camera. Positions are means over samples (blurred at silhouettes, and by depth of field:
    # this scene has a thin lens), motion uses the pixel-centre hit, so compare robustly.
    fov = f1.meta.scene_features["fov"]
    pos = n1["position"].transpose(1, 2, 0)
    hit = np.abs(pos).sum(-1) > 0
    xy, front = project(pos, prev, fov, 16, 16)
    y, x = np.mgrid[0:16, 0:16]
    err = np.hypot(x + 0.5 - n1["motion"][0] - xy[..., 0], y + 0.5 - n1["motion"][1] - xy[..., 1])
    ok = hit & front
    assert ok.mean() > 0.3
    assert np.median(err[ok]) < 0.5
    assert np.abs(n1["motion"]).max() > 0.5  # and the motion is not trivially small


@pytest.mark.slow
def test_count_20_end_to_end(tmp_path: Path) -> None:
    """The issue's acceptance run, at a small size: 20 random scenes, default object counts."""
    root = tmp_path / "ds20"
    t0 = time.perf_counter()
    cmd = [sys.executable, "-m", "mcdenoise.cli.main", "dataset", "--count", "20", "--out", str(root),
           "--spp", "4", "--ref-spp", "64", "--size", "32", "--seed", "2", "--no-progress"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
    seconds = time.perf_counter() - t0
    assert proc.returncode == 0, proc.stderr[-2000:]
    d = Dataset(root)
    assert len(d) == 20
    split_of = {e["scene"]: e["split"] for e in read_manifest(root)}
    assert len(split_of) == 20 and set(split_of.values()) == {"train", "val", "test"}
    kinds = set()
    for img in d.images():
        kinds.add(img.meta.extra["procedural"]["kind"])
        assert np.isfinite(img.read_noisy(["radiance"])["radiance"]).all()
        assert np.isfinite(img.read_reference(["radiance"])["radiance"]).all()
    assert kinds == {"indoor", "outdoor"}
    (tmp_path / "timing.json").write_text(json.dumps({"seconds": seconds}))
    print(f"\n--count 20 at 32x32, 4 spp, reference 64 spp: {seconds:.1f} s")


@pytest.fixture(scope="module")
def views_ds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("views") / "data"
    assert _run("--count", "2", "--views", "3", "--out", str(root), *TINY) == 0
    return root


def test_views_share_scene_and_split_not_camera(views_ds: Path) -> None:
    """Catches: views of one scene split across train/val/test (leakage), or views that are one
    picture three times (same camera or same seed)."""
    entries = read_manifest(views_ds)
    assert [e["path"] for e in entries] == [f"proc_{i:06d}/view_{v:03d}" for i in range(2) for v in range(3)]
    assert [e["view"] for e in entries] == [0, 1, 2] * 2
    for i in range(2):
        mine = [e for e in entries if e["scene"] == f"proc_{i:06d}"]
        assert len(mine) == 3 and len({e["split"] for e in mine}) == 1
        imgs = [read_image(views_ds / e["path"]) for e in mine]
        assert len({img.meta.extra["procedural"]["seed"] for img in imgs}) == 1
        assert len({img.meta.seed for img in imgs}) == 3
        # generator 4: the three inputs come from one stack (docs/DATASETS.md, "Speed")
        assert [img.meta.extra["view_stack"]["views"] for img in imgs] == [[0, 3]] * 3
        cams = [np.asarray(img.meta.extra["camera_to_world"]) for img in imgs]
        assert not np.allclose(cams[0], cams[1]) and not np.allclose(cams[1], cams[2])
        rads = [img.read_noisy(["radiance"])["radiance"] for img in imgs]
        assert all(np.isfinite(r).all() and r.mean() > 0 for r in rads)
        assert not np.array_equal(rads[0], rads[1])
    assert len(Dataset(views_ds)) == 6


def test_view_rendered_alone_is_the_same_image(views_ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Catches: a view's camera or pixels depending on which other views the process rendered
    before it (a resumed run or another shard would then write a different image)."""
    root = tmp_path / "v"
    shutil.copytree(views_ds, root)
    shutil.rmtree(root / "proc_000001" / "view_002")
    capsys.readouterr()
    assert _run("--count", "2", "--views", "3", "--out", str(root), *TINY) == 0
    out = capsys.readouterr().out
    # 2 scenes x 3 views = 6 images, 1 re-rendered: the count of finished ones must say 5
    # (it said -1 when it counted scenes x frames).
    assert "rendered 1 image(s)" in out and "5 already done" in out, out
    a, b = root / "proc_000001" / "view_002", views_ds / "proc_000001" / "view_002"
    np.testing.assert_array_equal(_radiance(a), _radiance(b))
    assert read_image(a).meta.extra["camera_to_world"] == read_image(b).meta.extra["camera_to_world"]
    assert read_manifest(root) == read_manifest(views_ds)


def test_views_with_frames_and_older_datasets_are_refused(ds: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Catches: resuming a dataset drawn by the previous scene pipeline (its images would mix with
    differently exposed ones), and an unsupported views x frames combination accepted."""
    capsys.readouterr()
    assert _run("--count", "1", "--views", "2", "--frames", "2", "--out", str(tmp_path / "vf"), *TINY) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "views" in err
    old = tmp_path / "old"
    shutil.copytree(ds, old)
    cfg = json.loads((old / "dataset.json").read_text())
    del cfg["generator"], cfg["views"]
    (old / "dataset.json").write_text(json.dumps(cfg))
    assert _run("--count", "3", "--out", str(old), *TINY) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "generator" in err


def test_view_stacks_are_fixed_by_the_options_and_bounded_in_memory() -> None:
    """Catches: stacks that depend on anything but the dataset's options (a resumed run would
    render a missing view in another stack, so with other samples), a stack holding more
    per-sample data in memory than STACK_BYTES (a large image must stream to disk view by view),
    and older generators stacked (their recipes would no longer give the same images)."""
    from mcdenoise.render.dataset_config import DatasetConfig
    from mcdenoise.render.procedural_image import STACK_BYTES, stacked, view_groups

    def cfg(size: int, views: int = 16, generator: int = 4) -> DatasetConfig:
        return DatasetConfig(count=1, width=size, height=size, spp=16, views=views, generator=generator)

    assert view_groups(cfg(128)) == [list(range(16))]
    assert view_groups(cfg(256)) == [list(range(a, a + 4)) for a in range(0, 16, 4)]
    assert view_groups(cfg(128, views=17)) == [list(range(16)), [16]]
    for c in (cfg(1024), cfg(128, generator=3), cfg(128, views=1)):
        assert not stacked(c) and view_groups(c) == [[v] for v in range(c.views)]
    for c in (cfg(128), cfg(256), cfg(362)):
        assert stacked(c) and max(map(len, view_groups(c))) * c.width * c.height * c.spp * 64 * 4 <= STACK_BYTES


def test_generators_4_and_3_check_views_cheaply_and_generator_2_still_renders(tmp_path: Path,
                                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Catches: a cheaper check applied to datasets of an older generator (their recipes would no
    longer render the same images: generator 3 checks extra views at 4 spp and the scene's preview
    at the input's settings, 2 everything at the input's settings), a generator-2 dataset resumed by
    the new default without a hint, and the check's spp and block not recorded."""
    from mcdenoise.render.dataset_config import GENERATOR, DatasetConfig
    from mcdenoise.render.procedural_image import check_settings
    from mcdenoise.render import RenderSettings

    assert GENERATOR == 4
    s = RenderSettings(spp=16, ref_spp=0, width=16, height=16)
    assert check_settings(DatasetConfig(count=1, generator=2), s) == (s, 1)
    got, block = check_settings(DatasetConfig(count=1, generator=3), s)
    assert (got.spp, block) == (4, 2) and got.width == 16
    assert check_settings(DatasetConfig(count=1, generator=3), s, first_view=True) == (s, 1)
    for first in (False, True):
        got, block = check_settings(DatasetConfig(count=1, generator=4), s, first_view=first)
        assert (got.spp, block) == (1, 4) and got.width == 16
    low = RenderSettings(spp=4, ref_spp=0, width=16, height=16)
    assert check_settings(DatasetConfig(count=1, generator=3), low) == (low, 1)

    args = ["--count", "1", "--views", "2", "--spp", "8", "--ref-spp", "0", "--size", "16", "--objects", "10-12",
            "--seed", "4", "--no-progress"]
    new, mid, old = tmp_path / "g4", tmp_path / "g3", tmp_path / "g2"
    assert _run("--out", str(new), *args) == 0
    assert _run("--out", str(mid), "--generator", "3", *args) == 0
    assert _run("--out", str(old), "--generator", "2", *args) == 0
    for d, g in ((new, 4), (mid, 3), (old, 2)):
        assert json.loads((d / "dataset.json").read_text())["generator"] == g

    def view(d: Path, v: int) -> dict:
        return json.loads((d / "proc_000000" / f"view_{v:03d}" / "meta.json").read_text())["extra"]["view"]

    for v in (0, 1):  # 8 spp: 1-spp checks on blocks of round(sqrt 8) = 3
        assert (view(new, v)["check_spp"], view(new, v)["check_block"]) == (1, 3)
    assert (view(mid, 1)["check_spp"], view(mid, 1)["check_block"]) == (4, 1)  # blocks of round(sqrt 2) = 1
    assert "check_spp" not in view(mid, 0) and "check_spp" not in view(old, 1)
    # view 0 is checked by the scene's own preview at the input's settings in versions 2 and 3: the same image
    np.testing.assert_array_equal(_radiance(mid / "proc_000000" / "view_000"), _radiance(old / "proc_000000" / "view_000"))
    capsys.readouterr()
    assert _run("--out", str(old), *args) == 1  # resumed without --generator 2: refused, and told how
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--generator 2" in err, err
    assert _run("--out", str(old), "--generator", "2", *args) == 0
