"""Scripts that read eval reports (scripts/compare_on_valscenes.py, scripts/bright_share_vs_ratio.py)."""

from __future__ import annotations

import json
from pathlib import Path

from repo_scripts import load_script


def _report(path: Path, folder: str, scenes: list[str], seeds: list[int], value: float) -> Path:
    rows = [{"image": f"{folder}{s}_128x128_d8_spp16_seed{seed}", "spp": 4, "method": m, "relmse": value * (i + 1),
             "psnr": 30.0 - i} for i, s in enumerate(scenes) for seed in seeds for m in ("old", "new")]
    path.write_text(json.dumps({"rows": rows}))
    return path


def test_compare_on_valscenes_keeps_scenes_apart_under_any_folder(tmp_path: Path) -> None:
    """Catches the scene key taken from the whole image path up to its first "_": images under
    `--data data/scene_inputs` then all became one scene "scene", the first image's figures stood for
    every scene, and the printed means were one scene's (it happened in campaign 25)."""
    cmp = load_script("compare_on_valscenes")
    scenes, seeds = ["bathroom", "salle-de-bain", "teapot-full"], [7, 8]
    for folder in ("", "scene_inputs/", "data/my_inputs/"):
        d = cmp.collect([str(_report(tmp_path / "r.json", folder, scenes, seeds, 0.1))])
        assert sorted(d) == sorted((s, seed, 4) for s in scenes for seed in seeds), folder
        assert d[("teapot-full", 8, 4)]["new"] == (0.1 * 3, 28.0)


def test_compare_on_valscenes_first_report_wins(tmp_path: Path) -> None:
    """Catches a later report overwriting a model's rows from an earlier one (the documented order)."""
    cmp = load_script("compare_on_valscenes")
    a = _report(tmp_path / "a.json", "x_y/", ["lamp"], [7], 0.1)
    b = _report(tmp_path / "b.json", "x_y/", ["lamp"], [7], 0.5)
    assert cmp.collect([str(a), str(b)])[("lamp", 7, 4)]["old"][0] == 0.1
    assert cmp.collect([str(b), str(a)])[("lamp", 7, 4)]["old"][0] == 0.5


def test_bright_share_and_spearman() -> None:
    """Catches a share taken over the darkest pixels or per channel instead of luminance, and a rank
    correlation that is not invariant to monotone maps (or has the wrong sign)."""
    import numpy as np

    bs = load_script("bright_share_vs_ratio")
    img = np.full((8, 8, 3), 1.0)
    img[2, 3] = (97.0, 97.0, 97.0)  # one small bright light: 97 of the image's 160 units of luminance
    assert bs.bright_share(img, 1) == np.float64(97.0 / 160.0)
    img[5, 5] = (0.0, 3.0, 0.0)  # luminance 1, the same as its neighbours: the share of one pixel stays put
    assert abs(bs.bright_share(img, 1) - 97.0 / 160.0) < 1e-12
    assert bs.bright_share(np.zeros((4, 4, 3)), 2) == 0.0
    x = np.array([0.1, 0.5, 0.2, 0.9, 0.3])
    assert abs(bs.spearman(x, np.exp(5 * x)) - 1.0) < 1e-12
    assert abs(bs.spearman(x, -x ** 3) + 1.0) < 1e-12


def test_compare_on_valscenes_scene_ratios_average_seeds_before_dividing(tmp_path: Path) -> None:
    """Catches a per-scene ratio taken per rendering and then averaged (or over the wrong scene's
    renderings): NEW / OLD must be the ratio of the two means over the seeds."""
    cmp = load_script("compare_on_valscenes")
    sc = {("bath", 7): {"old": (1.0, 0.0), "new": (2.0, 0.0)}, ("bath", 8): {"old": (3.0, 0.0), "new": (2.0, 0.0)},
          ("lamp", 7): {"old": (0.5, 0.0), "new": (0.25, 0.0)}}
    assert cmp.scene_ratios(sc, "old", "new") == {"bath": 1.0, "lamp": 0.5}
