"""The Cycles training set (``mcdenoise.render.cycles``): its scene draw, and pixel-only images in
the training code. The draw needs no Blender; the one render test is slow and skips without bpy."""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest
import torch

from mcdenoise.data.dataset import write_manifest
from mcdenoise.data.format import ImageMeta, write_image
from mcdenoise.data.sampler import importance_map
from mcdenoise.render.cycles.draw import draw_scene
from mcdenoise.render.cycles.worker import render_seed

HAS_BPY = importlib.util.find_spec("bpy") is not None


def test_the_draw_is_a_function_of_seed_and_index():
    """Catches a draw that reads a global or time-seeded generator (a dataset that does not come
    back from its recipe) or one that gives every scene the same description."""
    a = draw_scene(301, 5)
    assert json.loads(json.dumps(a)) == a == draw_scene(301, 5)
    assert draw_scene(301, 6) != a and draw_scene(302, 5) != a


def test_the_draw_has_what_real_scenes_have():
    """Catches a weight table or branch that silently drops an ingredient issue 19 asks for: small,
    very bright lights seen directly, window-lit rooms, glass, mirrors, fine textures, depth of field,
    brightness over orders of magnitude; and emissive objects grown into area lights."""
    scenes = [draw_scene(7, i) for i in range(300)]
    kinds = Counter(s["kind"] for s in scenes)
    assert set(kinds) == {"room", "outdoor", "studio"} and min(kinds.values()) > 30
    materials = Counter(o["material"]["kind"] for s in scenes for o in s["objects"])
    assert {"glass", "mirror", "metal", "textured", "emissive"} <= set(materials)
    small_bright = [li for s in scenes for li in s["lights"]
                    if li["type"] == "POINT" and li["radius"] < 0.01 and li["energy"] > 200 and li["visible"]]
    assert len(small_bright) > 10
    assert sum(s["kind"] == "room" and s["room"]["window"] is not None for s in scenes) > 30
    fine = [o["material"]["texture"]["scale"] for s in scenes for o in s["objects"] if "texture" in o["material"]]
    assert max(fine) > 40
    dof = sum("dof" in s["camera"] for s in scenes) / len(scenes)
    assert 0.2 < dof < 0.45
    exposure = [s["exposure"] for s in scenes]
    assert max(exposure) / min(exposure) > 50
    assert all(o["size"] <= 0.15 for s in scenes for o in s["objects"] if o["material"]["kind"] == "emissive")


def test_render_seeds_differ_between_renders():
    """Catches the reference or another spp reusing an input's seed (noise correlated with the
    target, which a model would learn to reproduce)."""
    seeds = {render_seed(301, i, k, ref) for i in range(50) for k in (4, 8, 16, 256) for ref in (False, True)}
    assert len(seeds) == 50 * 4 * 2


def test_importance_without_variance():
    """Catches the crop sampler requiring ``radiance_variance`` (a converted Cycles file has none:
    training on one failed with a missing-channel error): the 3x3 variance stands in, and a noisy
    half of the image scores higher than a clean half."""
    rng = np.random.default_rng(0)
    rad = np.full((3, 32, 32), 0.5, np.float32)
    rad[:, :, 16:] *= rng.exponential(1.0, (3, 32, 16)).astype(np.float32)
    score = importance_map({"radiance": rad}, None)
    assert np.isfinite(score).all() and (score >= 0).all()
    assert score[:, 17:].mean() > 3 * score[:, :15].mean()


def _pixel_dataset(root, n=3, split="val"):
    rng = np.random.default_rng(1)
    entries = []
    for i in range(n):
        ref = rng.uniform(0.1, 1, (3, 24, 24)).astype(np.float32)
        noisy = {"radiance": (ref * rng.exponential(1, ref.shape)).astype(np.float32),
                 "albedo": np.clip(ref, 0, 1), "normal": np.zeros_like(ref) + np.float32([0, 0, 1])[:, None, None]}
        meta = ImageMeta(width=24, height=24, spp=4, channels=list(noisy), scene=f"s{i}", renderer="test")
        write_image(root / f"s{i}", meta=meta, noisy=noisy, reference={"radiance": ref})
        entries.append({"path": f"s{i}", "scene": f"s{i}", "split": split})
    write_manifest(root, entries)


def test_validation_on_pixel_only_images(tmp_path):
    """Catches validation reading the baseline from per-sample data that a pixel-only image does
    not have (it failed with 'NoneType' has no attribute 'read'): the baseline is noisy.exr."""
    from mcdenoise.models.registry import build_model
    from mcdenoise.train.config import TrainConfig
    from mcdenoise.train.data import validation_batches
    from mcdenoise.train.trainer import data_config

    from mcdenoise.train.data import split_images

    _pixel_dataset(tmp_path)
    model = build_model("combine", "small")
    cfg = TrainConfig(model="combine", preset="small", data=str(tmp_path), loss="tonemapped_l2")
    batches = validation_batches(tmp_path, model, data_config(cfg))
    assert len(batches) == 3
    for b, im in zip(batches, split_images(tmp_path, "val")):
        want = torch.from_numpy(im.read_noisy(["radiance"])["radiance"])[None]
        assert torch.equal(b["noisy"], want)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_BPY, reason="needs bpy 4.5 (pip install 'mcdenoise[blender]')")
def test_the_dataset_command_renders_and_resumes(tmp_path):
    """Catches a Cycles dataset that is not a dataset (images that do not verify, a scene split
    across splits, a missing reference) and a rerun that renders again what is done."""
    out = tmp_path / "cyc"
    cmd = [sys.executable, "-m", "mcdenoise.render.cycles.dataset", "--out", str(out), "--count", "3", "--seed", "4",
           "--spp", "2", "4", "--ref-spp", "8", "--size", "32", "--split", "0.6,0.4,0"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert first.returncode == 0, first.stderr[-2000:]
    from mcdenoise.train.data import split_images

    images = split_images(out, "train") + split_images(out, "val")
    assert len(images) == 6 and all(im.has_reference and im.meta.spp in (2, 4) for im in images)
    splits = {}
    for e in json.loads((out / "manifest.json").read_text())["images"]:
        assert splits.setdefault(e["scene"], e["split"]) == e["split"]
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "rendered 0 scene(s)" in again.stdout
    other = subprocess.run(cmd[:-2] + ["--split", "0.5,0.5,0"], capture_output=True, text=True, timeout=600)
    assert other.returncode == 1 and "other settings" in other.stderr


def test_pixel_model_trains_on_per_sample_and_pixel_only_images_together(tmp_path):
    """Catches the refusals that stopped the first Cycles training run (a pixel-only image failed
    the ``spp_range`` checks of the crop sampler, and the OIDN precompute read samples it does not
    have): a combiner's batches draw from both kinds, the pixel-only image at its own spp, and its
    crop is exactly its stored noisy.exr."""
    from test_train_data import _dataset

    from mcdenoise.eval.oidn import oidn_available
    from mcdenoise.models.registry import build_model
    from mcdenoise.train.data import DataConfig, batch_source, precompute_oidn

    if not oidn_available():
        pytest.skip("pyoidn missing")
    per_sample = _dataset(tmp_path / "smp")
    pixel = tmp_path / "px"
    _pixel_dataset(pixel, split="train")
    model = build_model("combine", "small")
    cfg = DataConfig(crop=8, batch=4, workers=0, spp_range=(2, 4))
    src = batch_source(f"{per_sample},{pixel}", model, cfg)
    precompute_oidn(src.sampler.images, cfg, ["oidn"])  # refused a pixel-only image before
    kinds = Counter(im.samples is None for im in src.sampler.images)
    assert kinds[True] == 3 and kinds[False] >= 1
    seen_pixel_only = 0
    for i in range(30):
        c = src.sampler.draw(np.random.default_rng(i))
        im = next(x for x in src.sampler.images if x.path == c.path)
        if im.samples is None:
            seen_pixel_only += 1
            y, x = c.origin
            want = im.read_noisy(["radiance"], crop=(y, x, 8, 8))["radiance"]
            assert np.array_equal(c.inputs["radiance"], want)
    assert seen_pixel_only > 0


def test_the_recipe_command_parses_back_to_the_settings():
    """Catches a card that states a Cycles dataset command which renders other data than the
    dataset it names (a dropped or misspelt setting: spp list, split, reference spp)."""
    import shlex

    from mcdenoise.render.cycles.dataset import parser, recipe_command

    cfg = {"format": "mcdenoise-cycles-dataset", "version": 1, "seed": 301, "count": 48, "spp": [4, 8, 16],
           "ref_spp": 256, "size": 128, "fractions": [0.85, 0.15, 0.0], "blender": "4.5.15 LTS"}
    cmd = recipe_command("data/cycles_ref", cfg)
    a = parser().parse_args(shlex.split(cmd)[3:])
    assert (str(a.out), a.count, a.seed, a.spp, a.ref_spp, a.size, a.split) == \
        ("data/cycles_ref", 48, 301, [4, 8, 16], 256, 128, (0.85, 0.15, 0.0))
    assert "#" not in cmd and "&&" not in cmd  # cards join several dataset commands with " && "
