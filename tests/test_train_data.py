"""Training data: batch layout per model kind, determinism, ranks, spp per batch, crop importance,
noisy targets, validation batches. All on tiny synthetic image folders (no renderer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mcdenoise.data.channels import exposure_power, num_components
from mcdenoise.data.dataset import write_manifest
from mcdenoise.data.format import ImageMeta, pixel_stats, read_image, write_image
from mcdenoise.data.sampler import CropSampler, importance_map, window_scores
from mcdenoise.models.registry import build_model
from mcdenoise.models.sbmc import SBMC_CHANNELS
from mcdenoise.train.data import DataConfig, batch_source, training_batches, validation_batches

CHANNELS = list(dict.fromkeys(["radiance", "diffuse", "specular", "albedo", "normal", "depth", *SBMC_CHANNELS]))
SIZE = 24


def _image(root: Path, name: str, seed: int, *, spp: int = 8, reference: bool = True) -> dict[str, np.ndarray]:
    """One image: smooth left half, noisy right half (so importance sampling has a side to prefer)."""
    rng = np.random.default_rng(seed)
    noise = np.ones((1, 1, SIZE, SIZE), np.float32) * 0.01
    noise[..., SIZE // 2 :] = 2.0
    smp: dict[str, np.ndarray] = {}
    for c in CHANNELS:
        shape = (spp, num_components(c), SIZE, SIZE)
        smp[c] = rng.random(shape).astype(np.float16).astype(np.float32)
    clean = np.linspace(0.2, 1.0, SIZE, dtype=np.float32)[None, None, None, :] * np.ones((1, 3, SIZE, 1), np.float32)
    smp["diffuse"] = (clean + noise * rng.standard_normal((spp, 3, SIZE, SIZE))).astype(np.float32).clip(0)
    smp["specular"] = (0.1 * clean + noise * rng.random((spp, 3, SIZE, SIZE))).astype(np.float32)
    smp["radiance"] = smp["diffuse"] + smp["specular"]
    # Flat geometry and texture: the noise is the only thing that sets the right half apart.
    smp["normal"][:] = np.array([0, 0, 1], np.float32)[None, :, None, None]
    smp["albedo"][:] = 0.5
    meta = ImageMeta(width=SIZE, height=SIZE, spp=spp, channels=CHANNELS, scene=name, seed=seed,
                     scene_features={"fov": 40.0}, reference_spp=256 if reference else None)
    ref = None
    if reference:
        flat = np.full((3, SIZE, SIZE), 0.5, np.float32)  # no detail term either
        ref = {"radiance": 1.1 * flat, "diffuse": flat, "specular": 0.1 * flat}
    write_image(root / name, meta=meta, samples=smp, reference=ref, tile=8)
    return smp


def _dataset(root: Path, *, reference: bool = True, spp: int = 8) -> Path:
    entries = []
    for i, split in enumerate(["train", "train", "val"]):
        _image(root, f"s{i}", i, spp=spp, reference=reference)
        entries.append({"path": f"s{i}", "scene": f"s{i}", "split": split})
    write_manifest(root, entries)
    return root


@pytest.fixture(scope="module")
def ds(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _dataset(tmp_path_factory.mktemp("ds"))


def _eq(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert sorted(a) == sorted(b)
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)


@pytest.mark.parametrize("name", ["kpcn", "sbmc", "wskp"])
def test_batch_has_what_the_model_and_loss_read(ds: Path, name: str) -> None:
    """Bug caught: a batch missing a required channel, scene_features, or KPCN's branch targets,
    or with a per-row sample count a sample model cannot stack."""
    model = build_model(name, "small")
    cfg = DataConfig(crop=16, batch=3, workers=0)
    b = next(training_batches(ds, model, cfg))
    for c in model.required_channels():
        assert c in b, c
    assert b["target"].shape == (3, 3, 16, 16)
    if name == "kpcn":
        assert b["target:diffuse"].shape == b["target:specular"].shape == (3, 3, 16, 16)
        assert b["diffuse"].shape == (3, 3, 16, 16)
    if model.input_kind == "samples":
        s = b["radiance"].shape[1]
        assert b["radiance"].shape == (3, s, 3, 16, 16) and 2 <= s <= 8
        assert b["scene_features"].shape == (3, 5)
        assert b["spp"].tolist() == [s] * 3
    with torch.no_grad():
        assert model(b).shape == (3, 3, 16, 16)


def test_batches_are_a_function_of_seed_and_step(ds: Path) -> None:
    """Bug caught: batches that depend on the worker count, or a resumed run (start_step) that sees
    other crops than the uninterrupted run."""
    model = build_model("kpcn", "small")
    cfg = DataConfig(crop=16, batch=2, workers=0)
    it = training_batches(ds, model, cfg)
    first = [next(it) for _ in range(4)]
    resumed = next(training_batches(ds, model, cfg, start_step=3))
    _eq(first[3], resumed)
    par = training_batches(ds, model, DataConfig(crop=16, batch=2, workers=2, prefetch=2))
    for a in first:
        _eq(a, next(par))
    par.close()
    # Another seed gives other crops.
    other = next(training_batches(ds, model, DataConfig(crop=16, batch=2, workers=0, seed=1)))
    assert not torch.equal(other["diffuse"], first[0]["diffuse"])


def test_ranks_split_the_global_batch(ds: Path) -> None:
    """Bug caught: ranks drawing overlapping or different rows than one process with the whole batch."""
    model = build_model("sbmc", "small")
    cfg = DataConfig(crop=8, batch=4, workers=0)
    whole = batch_source(ds, model, cfg)[5]
    parts = [batch_source(ds, model, cfg, rank=r, world_size=2)[5] for r in range(2)]
    for k in whole:
        torch.testing.assert_close(torch.cat([p[k] for p in parts]), whole[k], rtol=0, atol=0)
    with pytest.raises(ValueError, match="divisible"):
        batch_source(ds, model, DataConfig(batch=3), world_size=2)


def test_sample_models_get_one_spp_per_batch_in_range(ds: Path) -> None:
    """Bug caught: a fixed spp (no 2..8 variety), or rows of a batch with different S."""
    model = build_model("sbmc", "small")
    src = batch_source(ds, model, DataConfig(crop=8, batch=2, workers=0, augment=False))
    counts = {src[t]["radiance"].shape[1] for t in range(40)}
    assert counts <= set(range(2, 9)) and len(counts) >= 5


@pytest.mark.parametrize("name", ["sbmc", "kpcn"])
def test_exposure_scales_a_crop_and_its_target_together(ds: Path, name: str) -> None:
    """Bugs caught: a target left at the rendered exposure while its inputs move (the network would
    learn to change brightness), variances scaled by k instead of k**2, albedo, normals or depth
    scaled as if they were radiance, factors outside the range, and exposure augmentation that
    draws from the crop's stream when it is off (every earlier run would see other crops)."""
    model = build_model(name, "small")
    base = DataConfig(crop=8, batch=3, workers=0, spp_range=(4, 4))
    plain = batch_source(ds, model, base)
    lit = batch_source(ds, model, DataConfig(crop=8, batch=3, workers=0, spp_range=(4, 4), exposure=(0.1, 10.0)))
    ks = []
    for t in range(6):
        a, b = plain[t], lit[t]
        assert a.keys() == b.keys()
        k = (b["target"].flatten(1) / a["target"].flatten(1))[:, 0]
        ks += k.tolist()
        for key in a:
            if key == "spp":
                continue
            p = exposure_power("radiance" if key == "target" else key.removeprefix("target:"))
            shape = (-1,) + (1,) * (a[key].dim() - 1)
            torch.testing.assert_close(b[key], a[key] * k.view(shape) ** p, rtol=1e-5, atol=0, msg=key)
    ks = np.array(ks)
    assert ks.min() >= 0.1 * (1 - 1e-6) and ks.max() <= 10 * (1 + 1e-6)
    assert ks.min() < 0.5 and ks.max() > 2  # drawn over the range, not a constant
    # Off (the default), the crops are those of a run without the option, bit for bit.
    _eq(plain[2], batch_source(ds, model, DataConfig(crop=8, batch=3, workers=0, spp_range=(4, 4), exposure=None))[2])


def test_exposure_power_of_the_channels() -> None:
    """Bug caught: a radiance-like channel (or an OIDN output fed to the combiner) left unscaled,
    or a guide scaled, by the exposure augmentation."""
    assert [exposure_power(c) for c in ("radiance", "diffuse", "specular", "oidn", "oidn_pf")] == [1] * 5
    assert exposure_power("radiance_variance") == exposure_power("specular_variance") == 2
    assert [exposure_power(c) for c in ("albedo", "normal", "depth", "albedo_variance", "subpixel")] == [0] * 5


def test_pixel_inputs_recomputed_from_the_drawn_subset(ds: Path) -> None:
    """Bug caught: pixel models fed the full-spp noisy.exr although spp_range asked for fewer samples."""
    model = build_model("kpcn", "small")
    src = batch_source(ds, model, DataConfig(crop=8, batch=1, workers=0, augment=False))
    im = read_image(ds / "s0")
    c = src.sampler.draw(np.random.default_rng([0, 7, 1]), spp=None)
    y0, x0 = c.origin
    smp = im.samples.read(["diffuse"], crop=(y0, x0, 8, 8), samples=c.samples)["diffuse"]
    if c.path.name == "s0":
        mean, var = pixel_stats(smp)
        np.testing.assert_array_equal(c.inputs["diffuse"], mean)
        np.testing.assert_array_equal(c.inputs["diffuse_variance"], var)
    b = src[7]
    assert 2 <= int(b["spp"][0]) <= 8


def test_importance_sampling_prefers_noisy_regions(ds: Path) -> None:
    """Bug caught: 'importance' crops that are as often smooth as uniform ones (KPCN Sec. 5.1), or
    that never show smooth regions at all (no auto-accept)."""
    im = read_image(ds / "s0")
    kw = dict(crop=8, channels=["radiance"], kind="pixels", seed=3)
    uni = CropSampler([im], sampling="uniform", **kw)
    imp = CropSampler([im], sampling="importance", accept_after=4, **kw)
    right_u = np.mean([uni[i].origin[1] >= SIZE // 2 for i in range(300)])
    xs = np.array([imp[i].origin[1] for i in range(300)])
    right_i = np.mean(xs >= SIZE // 2)
    assert right_i > right_u + 0.2, (right_i, right_u)
    assert (xs + 8 <= SIZE // 2).any()  # some entirely smooth crops still appear
    assert imp[11].origin == imp[11].origin


def test_window_scores_are_window_means() -> None:
    """Bug caught: an off-by-one in the summed-area table (window scores shifted by a pixel)."""
    rng = np.random.default_rng(0)
    s = rng.random((9, 11))
    w = window_scores(s, 4)
    assert w.shape == (6, 8)
    np.testing.assert_allclose(w[2, 5], s[2:6, 5:9].mean())
    noisy = {"radiance": np.ones((3, 9, 11), np.float32), "radiance_variance": np.zeros((3, 9, 11), np.float32)}
    noisy["radiance_variance"][:, 4, 4] = 1.0
    m = importance_map(noisy, None)
    assert m.argmax() == 4 * 11 + 4 and np.isfinite(m).all()


def test_noisy_target_uses_disjoint_held_out_samples(tmp_path: Path) -> None:
    """Bug caught: a Noise2Noise target that shares samples with the input (correlated noise makes
    the loss biased toward the input), or that still demands a reference.exr."""
    root = _dataset(tmp_path, reference=False)
    model = build_model("kpcn", "small")
    cfg = DataConfig(crop=8, batch=2, workers=0, target="noisy", augment=False)
    src = batch_source(root, model, cfg)
    assert src.sampler.spp_range == (2, 4)  # capped: half the 8 samples stay for the target
    c = src.sampler.draw(np.random.default_rng([0, 2, 1]))
    assert c.samples and c.target_samples
    assert not set(c.samples) & set(c.target_samples) and len(c.samples) + len(c.target_samples) == 8
    y0, x0 = c.origin
    held = read_image(c.path).samples.read(["diffuse"], crop=(y0, x0, 8, 8), samples=c.target_samples)["diffuse"]
    np.testing.assert_allclose(c.reference["diffuse"], held.mean(axis=0), rtol=1e-6)
    b = src[2]
    assert b["target"].shape == (2, 3, 8, 8) and "target:specular" in b
    val = validation_batches(root, model, cfg)
    assert len(val) == 1 and val[0]["spp"].item() == 4
    with pytest.raises(ValueError, match="no reference"):
        batch_source(root, model, DataConfig(crop=8, batch=2))


def test_validation_batches_whole_images(ds: Path) -> None:
    """Bug caught: validation crops drawn at random (metrics not comparable across steps)."""
    model = build_model("sbmc", "small")
    cfg = DataConfig(crop=8, batch=2, workers=0)
    a = validation_batches(ds, model, cfg)
    b = validation_batches(ds, model, cfg, max_images=5)
    assert len(a) == 1
    _eq(a[0], b[0])
    assert a[0]["radiance"].shape == (1, 8, 3, SIZE, SIZE) and a[0]["target"].shape == (1, 3, SIZE, SIZE)
    assert validation_batches(ds, model, cfg, max_images=0) == []


def test_data_config_rejects_bad_settings() -> None:
    """Bug caught: a typo in sampling/target silently falling back to a default."""
    with pytest.raises(ValueError, match="sampling"):
        DataConfig(sampling="importnace")
    with pytest.raises(ValueError, match="target"):
        DataConfig(target="clean")
    with pytest.raises(ValueError, match="spp_range"):
        DataConfig(spp_range=(3, 2))
    assert DataConfig(spp_range=[2, 4]).spp_range == (2, 4)  # JSON lists become tuples
    with pytest.raises(ValueError, match="exposure"):
        DataConfig(exposure=(0.0, 2.0))
    with pytest.raises(ValueError, match="exposure"):
        DataConfig(exposure=(4.0, 2.0))
    assert DataConfig(exposure=[0.5, 2]).exposure == (0.5, 2.0)


def test_several_datasets_train_on_their_union(ds: Path, tmp_path: Path) -> None:
    """Bugs caught: ``--data a,b`` reading only the first dataset (or treating "a,b" as one missing
    folder), validation ignoring the second dataset's val split, a run of two datasets resuming
    against a third (the manifest hash must name both), and a single dataset's hash changing so that
    older runs no longer resume."""
    import dataclasses
    import json

    from mcdenoise.train.config import ConfigError, TrainConfig, manifest_hash
    from mcdenoise.data.dataset import dataset_dirs
    from mcdenoise.train.loop import train

    other = tmp_path / "other"  # other image names, so its manifest differs from ds's
    entries = []
    for i, split in enumerate(["train", "train", "val"]):
        _image(other, f"t{i}", 10 + i)
        entries.append({"path": f"t{i}", "scene": f"t{i}", "split": split})
    write_manifest(other, entries)
    spec = f"{ds},{other}"
    assert dataset_dirs(spec) == [ds, other]
    with pytest.raises(ValueError, match="empty"):
        dataset_dirs(f"{ds},,{other}")
    model = build_model("kpcn", "small")
    cfg = DataConfig(crop=8, batch=2, workers=0, spp_range=(2, 4))
    assert len(batch_source(spec, model, cfg).sampler.images) == 4  # 2 train images in each
    assert len(validation_batches(spec, model, cfg)) == 2
    assert manifest_hash(str(ds)) != manifest_hash(spec) != manifest_hash(f"{other},{ds}")
    import hashlib
    assert manifest_hash(str(ds)) == hashlib.sha256((ds / "manifest.json").read_bytes()).hexdigest()

    tc = TrainConfig(model="wskp", data=spec, steps=2, batch=2, crop=8, workers=0, progress=False, val_every=0)
    train(tc, tmp_path / "run")
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["manifest_sha256"] == manifest_hash(spec)
    with pytest.raises(ConfigError, match="manifest"):  # same run, other data: refused
        train(dataclasses.replace(tc, data=str(ds), steps=3), tmp_path / "run", resume=True)
    with pytest.raises(ConfigError, match="no manifest.json"):
        train(dataclasses.replace(tc, data=f"{ds},{tmp_path / 'missing'}"), tmp_path / "run2")
