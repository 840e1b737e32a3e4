"""Issue 18 item "model cards must reproduce": a procedural dataset records the Mitsuba variant it
was rendered with (dataset.json and the manifest), the manifest hash a run resumes against covers
the render settings, older datasets keep their manifest hash, and model cards state the variant.
No rendering: the manifest is rebuilt from dataset.json and a list of finished folders."""

from __future__ import annotations

import argparse
import hashlib
import json
import shlex
from pathlib import Path

import pytest

from mcdenoise.cli import dataset as dataset_cli
from mcdenoise.data.dataset import read_manifest, read_manifest_settings
from mcdenoise.errors import FormatError
from mcdenoise.render.cycles.dataset import parser as cycles_parser
from mcdenoise.models.ship import dataset_command
from mcdenoise.models.weights import SHIPPED_DIR, WeightsError
from mcdenoise.render import _mitsuba as M
from mcdenoise.render.procedural_dataset import (
    DatasetConfig,
    _write_config,
    rebuild_manifest,
    recorded_variant,
)
from mcdenoise.train.config import manifest_hash

#: How a card states a Cycles dataset (mcdenoise.render.cycles.dataset.recipe_command).
CYCLES_COMMAND = "python -m mcdenoise.render.cycles.dataset"

DONE = {"proc_000000", "proc_000001", "proc_000002"}


def _dataset(root: Path, cfg: DatasetConfig) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset.json").write_text(json.dumps(cfg.to_json(), indent=1) + "\n")
    rebuild_manifest(root, DONE)
    return root


def _old_manifest_bytes(root: Path) -> bytes:
    """manifest.json exactly as versions before the settings block wrote it."""
    doc = {"format": "mcdenoise-dataset", "version": 1, "images": read_manifest(root)}
    return (json.dumps(doc, indent=1) + "\n").encode()


def _meta(folder: Path, variant: str) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "meta.json").write_text(json.dumps({"renderer": f"mitsuba 3.9.1 ({variant}) / mcdenoise 0.1.0"}))


def test_manifest_hash_covers_render_settings_and_variant(tmp_path: Path) -> None:
    """Bug caught (issue 18): the manifest hash covered only paths and splits, so a run resumed (or
    a card claimed reproduction) on data rendered with other spp, size, depth or another Mitsuba
    variant; and the variant was recorded nowhere."""
    base = DatasetConfig(count=3, seed=5, spp=8, ref_spp=64, width=32, height=32, variant="llvm_ad_rgb")
    a = _dataset(tmp_path / "a", base)
    settings = read_manifest_settings(a)
    assert settings is not None and settings["variant"] == "llvm_ad_rgb" and settings["spp"] == 8
    assert json.loads((a / "dataset.json").read_text())["variant"] == "llvm_ad_rgb"
    for i, change in enumerate([{"spp": 16}, {"ref_spp": 128}, {"width": 48}, {"max_depth": 8}, {"world": "rich"},
                                {"variant": "cuda_ad_rgb"}, {"rr_depth": 2}]):
        b = _dataset(tmp_path / f"b{i}", DatasetConfig(**{**base.__dict__, **change}))
        assert read_manifest(b) == read_manifest(a)  # same images and splits ...
        assert manifest_hash(b) != manifest_hash(a), change  # ... yet other data


def test_old_datasets_keep_their_manifest_hash(tmp_path: Path) -> None:
    """Bug caught: recording the settings changed the manifest of datasets made before, so every
    run on data/rich_ref etc. (campaigns/c1) would refuse to resume ('manifest.json differs').
    A dataset.json with no variant rebuilds the old manifest byte for byte."""
    old = _dataset(tmp_path / "old", DatasetConfig(count=3, seed=5, spp=8, ref_spp=64, width=32, height=32))
    assert "variant" not in json.loads((old / "dataset.json").read_text())
    assert "rr_depth" not in json.loads((old / "dataset.json").read_text())  # added later, at its old value
    assert read_manifest_settings(old) is None
    assert manifest_hash(old) == hashlib.sha256(_old_manifest_bytes(old)).hexdigest()


def test_resuming_an_old_dataset_keeps_it_and_checks_the_images_variant(tmp_path: Path) -> None:
    """Bug caught: a rerun of a dataset made before the variant was recorded refused ('variant:
    None there') or rewrote dataset.json (changing its manifest hash); and a rerun with another
    variant than its images mixed CPU and GPU pixels in one dataset."""
    cfg = DatasetConfig(count=3, seed=5, spp=8, ref_spp=64, width=32, height=32)
    old = _dataset(tmp_path / "old", cfg)
    before = (old / "dataset.json").read_bytes()
    _meta(old / "proc_000000", "llvm_ad_rgb")
    _write_config(old, DatasetConfig(**{**cfg.__dict__, "variant": "llvm_ad_rgb"}))
    assert (old / "dataset.json").read_bytes() == before
    assert recorded_variant(old) == "llvm_ad_rgb"
    with pytest.raises(FormatError, match="variant") as e:
        _write_config(old, DatasetConfig(**{**cfg.__dict__, "variant": "cuda_ad_rgb"}))
    assert "\n" not in str(e.value)
    # A dataset that records its variant refuses a rerun with another one.
    new = _dataset(tmp_path / "new", DatasetConfig(**{**cfg.__dict__, "variant": "llvm_ad_rgb"}))
    with pytest.raises(FormatError, match="variant"):
        _write_config(new, DatasetConfig(**{**cfg.__dict__, "variant": "cuda_ad_rgb"}))


def test_render_dataset_fixes_the_process_variant(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bug caught: dataset.json written with no variant (or 'auto') by a caller that leaves it
    unset: the recorded variant is the one the process resolves, never 'auto'."""
    monkeypatch.delenv("MCDENOISE_VARIANT", raising=False)
    monkeypatch.setattr(M, "_MI", None)
    monkeypatch.setattr(M, "_REQUESTED", None)
    monkeypatch.setattr(M, "cuda_available", lambda: False)
    assert M.process_variant() == "llvm_ad_rgb"
    monkeypatch.setattr(M, "_REQUESTED", "cuda_ad_rgb")
    assert M.process_variant() == "cuda_ad_rgb"
    assert M.variant_of_renderer("mitsuba 3.9.1 (cuda_ad_rgb) / mcdenoise 0.1.0") == "cuda_ad_rgb"
    assert M.variant_of_renderer("") is None
    with pytest.raises(Exception, match="variant"):
        DatasetConfig(count=1, variant="auto").check()


def _parse(cmd: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    dataset_cli.add_parser(p)
    argv = shlex.split(cmd)
    assert argv[:2] == ["mcdenoise", "dataset"]
    return p.parse_args(argv[2:])


def test_card_dataset_command_states_the_variant(tmp_path: Path) -> None:
    """Bug caught (issue 18): a card's dataset command omitted the Mitsuba variant, so on a GPU host
    it rendered other pixels (auto = cuda_ad_rgb). Old datasets take it from their images; a
    dataset naming none cannot state its command."""
    new = _dataset(tmp_path / "new", DatasetConfig(count=3, spp=4, variant="cuda_ad_rgb"))
    assert _parse(dataset_command(new)).variant == "cuda_ad_rgb"
    old = _dataset(tmp_path / "old", DatasetConfig(count=3, spp=4))
    with pytest.raises(WeightsError, match="variant"):
        dataset_command(old)
    _meta(old / "proc_000001", "llvm_ad_rgb")
    assert _parse(dataset_command(old)).variant == "llvm_ad_rgb"


def test_card_dataset_command_names_the_scene_pipeline(tmp_path: Path) -> None:
    """Bug caught: a dataset of the current pipeline got a recipe without ``--generator``, which a
    later default (a new pipeline) would render differently."""
    from mcdenoise.render.dataset_config import GENERATOR

    root = _dataset(tmp_path / "d", DatasetConfig(count=3, spp=4, variant="llvm_ad_rgb"))
    assert _parse(dataset_command(root)).generator == GENERATOR


def test_shipped_cards_state_the_variant_they_were_rendered_with() -> None:
    """Bug caught (issue 18): the shipped cards' dataset commands omitted the variant (they were
    rendered on a CPU: llvm_ad_rgb, what `--variant auto` picks without a GPU)."""
    cards = sorted(SHIPPED_DIR.glob("*.json"))
    assert cards
    for path in cards:
        # A model trained on several datasets states one command per dataset, joined by " && ".
        for cmd in json.loads(path.read_text())["dataset"]["command"].split(" && "):
            if cmd.startswith(CYCLES_COMMAND):  # a Cycles set: no Mitsuba variant, its own arguments
                args = cycles_parser().parse_args(shlex.split(cmd)[len(CYCLES_COMMAND.split()):])
                assert args.count > 0 and args.ref_spp > 0, path.name
                continue
            assert _parse(cmd).variant == "llvm_ad_rgb", path.name


def test_russian_roulette_depth_reaches_the_renders_and_the_recipe(tmp_path: Path) -> None:
    """Bug caught: ``--rr-depth`` parsed but not passed to the renderer (datasets silently at 5), a
    recipe that drops it (the card's command would render other pixels), or a value out of range
    accepted."""
    from mcdenoise.render.procedural_image import _settings

    args = _parse("mcdenoise dataset --out d --count 2 --rr-depth 2")
    assert args.rr_depth == 2
    cfg = DatasetConfig(count=2, rr_depth=2)
    assert _settings(cfg, 0).rr_depth == 2 and _settings(DatasetConfig(count=2), 0).rr_depth == 5
    root = _dataset(tmp_path / "d", DatasetConfig(count=3, spp=4, variant="llvm_ad_rgb", rr_depth=3))
    assert _parse(dataset_command(root)).rr_depth == 3
    assert "--rr-depth" not in dataset_command(_dataset(tmp_path / "e", DatasetConfig(count=3, spp=4, variant="llvm_ad_rgb")))
    with pytest.raises(Exception, match="rr_depth"):
        DatasetConfig(count=2, rr_depth=0).check()


def _generate_kwargs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, cfg: DatasetConfig) -> dict:
    """The keyword arguments ``render_procedural_image`` passes to the generator for ``cfg``."""
    import mcdenoise.render.procedural as procedural
    from mcdenoise.render.procedural_image import render_procedural_image

    seen: dict = {}

    class Drawn(Exception):
        pass

    def fake_generate(seed: int, **kw: object) -> None:
        seen.update(kw)
        raise Drawn

    monkeypatch.setattr(procedural, "generate", fake_generate)
    with pytest.raises(Drawn):
        render_procedural_image(cfg, tmp_path, 0, ["proc_000000/view_000"])
    return seen


@pytest.mark.parametrize("field, flag, world, bad", [
    ("small_emitters", "--small-emitters", "rich", ({"small_emitters": 1.5}, {"small_emitters": -0.1},
                                                    {"small_emitters": 0.5, "world": "classic"})),
    ("strong_dof", "--strong-dof", "detailed", ({"strong_dof": 1.5}, {"strong_dof": -0.1}, {"strong_dof": True})),
])
def test_scene_rates_reach_the_generator_and_the_recipe(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, field: str,
                                                        flag: str, world: str, bad: tuple) -> None:
    """Bug caught: ``--small-emitters`` or ``--strong-dof`` parsed but not passed to the generator (the
    dataset would silently keep every small emitter, or the ordinary lens), a recipe that drops it, a
    manifest hash blind to it, an old dataset.json that gains the key (its manifest hash would
    change), or a rate out of [0, 1] (or small emitters with the classic world, which draws none)
    accepted."""
    assert getattr(_parse(f"mcdenoise dataset --out d --count 2 --world {world} {flag} 0.25"), field) == 0.25
    seen = _generate_kwargs(tmp_path, monkeypatch, DatasetConfig(count=1, world="detailed", views=2, **{field: 0.0}))
    assert seen[field] == 0.0 and seen["world"] == "detailed"
    base = DatasetConfig(count=3, spp=4, variant="llvm_ad_rgb", world=world)
    a = _dataset(tmp_path / "a", base)
    b = _dataset(tmp_path / "b", DatasetConfig(**{**base.__dict__, field: 0.25}))
    assert field not in json.loads((a / "dataset.json").read_text())
    assert manifest_hash(a) != manifest_hash(b)
    assert getattr(_parse(dataset_command(b)), field) == 0.25
    assert flag not in dataset_command(a)
    for wrong in bad:
        with pytest.raises(Exception, match=field):
            DatasetConfig(**{**base.__dict__, **wrong}).check()
    DatasetConfig(**{**base.__dict__, field: 0.0}).check()
    if field == "strong_dof":  # any world has a lens
        DatasetConfig(**{**base.__dict__, field: 0.0, "world": "classic"}).check()
