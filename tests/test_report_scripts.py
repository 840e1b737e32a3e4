"""Scripts that read eval reports (scripts/compare_on_valscenes.py, scripts/bright_share_vs_ratio.py)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"_{name}", ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _report(path: Path, folder: str, scenes: list[str], seeds: list[int], value: float) -> Path:
    rows = [{"image": f"{folder}{s}_128x128_d8_spp16_seed{seed}", "spp": 4, "method": m, "relmse": value * (i + 1),
             "psnr": 30.0 - i} for i, s in enumerate(scenes) for seed in seeds for m in ("old", "new")]
    path.write_text(json.dumps({"rows": rows}))
    return path


def test_compare_on_valscenes_keeps_scenes_apart_under_any_folder(tmp_path: Path) -> None:
    """Catches the scene key taken from the whole image path up to its first "_": images under
    `--data data/scene_inputs` then all became one scene "scene", the first image's figures stood for
    every scene, and the printed means were one scene's (it happened in campaign 25)."""
    cmp = _load("compare_on_valscenes")
    scenes, seeds = ["bathroom", "salle-de-bain", "teapot-full"], [7, 8]
    for folder in ("", "scene_inputs/", "data/my_inputs/"):
        d = cmp.collect([str(_report(tmp_path / "r.json", folder, scenes, seeds, 0.1))])
        assert sorted(d) == sorted((s, seed, 4) for s in scenes for seed in seeds), folder
        assert d[("teapot-full", 8, 4)]["new"] == (0.1 * 3, 28.0)


def test_compare_on_valscenes_first_report_wins(tmp_path: Path) -> None:
    """Catches a later report overwriting a model's rows from an earlier one (the documented order)."""
    cmp = _load("compare_on_valscenes")
    a = _report(tmp_path / "a.json", "x_y/", ["lamp"], [7], 0.1)
    b = _report(tmp_path / "b.json", "x_y/", ["lamp"], [7], 0.5)
    assert cmp.collect([str(a), str(b)])[("lamp", 7, 4)]["old"][0] == 0.1
    assert cmp.collect([str(b), str(a)])[("lamp", 7, 4)]["old"][0] == 0.5


def test_bright_share_and_spearman() -> None:
    """Catches a share taken over the darkest pixels or per channel instead of luminance, and a rank
    correlation that is not invariant to monotone maps (or has the wrong sign)."""
    import numpy as np

    bs = _load("bright_share_vs_ratio")
    img = np.full((8, 8, 3), 1.0)
    img[2, 3] = (97.0, 97.0, 97.0)  # one small bright light: 97 of the image's 160 units of luminance
    assert bs.bright_share(img, 1) == np.float64(97.0 / 160.0)
    img[5, 5] = (0.0, 3.0, 0.0)  # luminance 1, the same as its neighbours: the share of one pixel stays put
    assert abs(bs.bright_share(img, 1) - 97.0 / 160.0) < 1e-12
    assert bs.bright_share(np.zeros((4, 4, 3)), 2) == 0.0
    x = np.array([0.1, 0.5, 0.2, 0.9, 0.3])
    assert abs(bs.spearman(x, np.exp(5 * x)) - 1.0) < 1e-12
    assert abs(bs.spearman(x, -x ** 3) + 1.0) < 1e-12
