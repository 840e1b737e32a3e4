"""mcdenoise eval --scenes: scene files with given references (issue 19 item 1)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.cli.main import main
from mcdenoise.eval.scenes import ScenesError, find_scene_cases, prepare_scene_inputs

SCENE = """<scene version="3.0.0">
  <default name="resx" value="16"/><default name="resy" value="16"/>
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="$resx"/><integer name="height" value="$resy"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
</scene>
"""


@pytest.fixture()
def scenes(tmp_path: Path) -> Path:
    root = tmp_path / "valscenes"
    for name in ("ball", "noref"):
        (root / name).mkdir(parents=True)
        (root / name / "scene.xml").write_text(SCENE)
    (root / "refs").mkdir()
    ref = np.full((16, 16, 3), 0.25, np.float16)
    np.save(root / "refs" / "ball_16_spp64_d4.npy", ref)
    np.save(root / "refs" / "ball_32_spp64_d4.npy", np.zeros((32, 32, 3), np.float16))  # larger: not picked
    return root


def test_cases_pair_scenes_with_the_smallest_reference(scenes: Path, capsys: pytest.CaptureFixture) -> None:
    """Catches a scene scored against another size's reference, or scenes without one kept."""
    cases = find_scene_cases(scenes)
    assert [(c.name, c.width, c.height, c.max_depth, c.reference_spp) for c in cases] == [("ball", 16, 16, 4, 64)]
    assert "no reference for noref" in capsys.readouterr().err
    with pytest.raises(ScenesError, match="nope"):
        find_scene_cases(scenes, names=["nope"])


@pytest.mark.render
def test_inputs_are_rendered_once_with_the_given_reference(scenes: Path, tmp_path: Path) -> None:
    """Catches the reference not stored (eval would find none), a stale folder reused after the
    settings changed, and a rerun that renders again (minutes per scene at full size)."""
    from mcdenoise.data.image_folder import ImageFolder

    before = sorted(p.name for p in scenes.rglob("*"))
    cases = find_scene_cases(scenes)
    [folder] = prepare_scene_inputs(cases, tmp_path / "work", spp=4, seed=3, progress=False)
    im = ImageFolder(folder)
    assert im.meta.spp == 4 and im.meta.reference_spp == 64 and im.meta.width == 16
    np.testing.assert_array_equal(im.read_reference(["radiance"])["radiance"], np.full((3, 16, 16), 0.25, np.float32))
    stamp = (folder / "samples.bin").stat().st_mtime_ns
    assert prepare_scene_inputs(cases, tmp_path / "work", spp=4, seed=3, progress=False) == [folder]
    assert (folder / "samples.bin").stat().st_mtime_ns == stamp
    [other] = prepare_scene_inputs(cases, tmp_path / "work", spp=4, seed=4, progress=False)
    assert other != folder
    assert sorted(p.name for p in scenes.rglob("*")) == before  # the scenes folder is only read
    # Inputs of an mcdenoise before the canonical emitter order (no mark in meta.json) hold one draw
    # of Mitsuba's load-dependent order: they are rendered again, once.
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["extra"]["emitter_sampling"] == "canonical-order"
    del meta["extra"]["emitter_sampling"]
    (folder / "meta.json").write_text(json.dumps(meta))
    assert prepare_scene_inputs(cases, tmp_path / "work", spp=4, seed=3, progress=False) == [folder]
    assert (folder / "samples.bin").stat().st_mtime_ns != stamp
    assert json.loads((folder / "meta.json").read_text())["extra"]["emitter_sampling"] == "canonical-order"


@pytest.mark.render
def test_eval_cli_scores_scene_files(scenes: Path, tmp_path: Path) -> None:
    """Catches --scenes not reaching the evaluation (empty report) or spp beyond the rendered inputs."""
    out = tmp_path / "report"
    rc = main(["eval", "--scenes", str(scenes), "--spp", "2", "4", "--out", str(out), "--work", str(tmp_path / "w"),
               "--no-oidn", "--no-classic", "--no-html", "--no-progress"])
    assert rc == 0
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert {(r["method"], r["spp"]) for r in rows} == {("noisy", 2), ("noisy", 4)}


@pytest.mark.render
def test_eval_cli_renders_each_seed_and_reports_their_spread(scenes: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    """Catches several --render-seed values collapsing into one rendering (the same folder reused,
    so no spread), the seed missing from the report's images, or the spread left off the summary."""
    out = tmp_path / "report"
    rc = main(["eval", "--scenes", str(scenes), "--spp", "2", "--out", str(out), "--work", str(tmp_path / "w"),
               "--render-seed", "3", "4", "--no-oidn", "--no-classic", "--no-progress"])
    assert rc == 0
    doc = json.loads((out / "results.json").read_text())
    assert sorted(im["seed"] for im in doc["images"]) == [3, 4]
    (spread,) = doc["seed_spread"]
    assert spread["method"] == "noisy" and spread["seeds"] == [3, 4] and spread["images_per_seed"] == 1
    by_seed = {im["seed"]: im["id"] for im in doc["images"]}
    relmse = {r["image"]: r["relmse"] for r in doc["rows"]}
    assert spread["relmse"] == [relmse[by_seed[3]], relmse[by_seed[4]]]
    assert spread["relmse"][0] != spread["relmse"][1]  # two renderings, not one twice
    assert "Spread over the 2 render seeds (3, 4)" in capsys.readouterr().out
    assert "Spread over the 2 render seeds (3, 4)" in (out / "index.html").read_text()
    rc = main(["eval", "--scenes", str(scenes), "--spp", "2", "--out", str(out), "--work", str(tmp_path / "w"),
               "--render-seed", "3", "3", "--no-oidn", "--no-classic", "--no-progress"])
    assert rc != 0 and "--render-seed: a seed given twice (3 3)" in capsys.readouterr().err
