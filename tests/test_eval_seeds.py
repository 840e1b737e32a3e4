"""The spread of an evaluation's means over render seeds (mcdenoise/eval/seeds.py).

Each test names the bug it catches."""

from __future__ import annotations

import numpy as np

from mcdenoise.eval.seeds import seed_spread, spread_text


def _doc(values: dict[tuple[str, int, str, int], tuple[float, float]]):
    """rows and images from {(method, spp, scene, seed): (relmse, psnr)}."""
    images, rows = {}, []
    for (method, spp, scene, seed), (r, p) in values.items():
        iid = f"w/{scene}_seed{seed}"
        images[iid] = {"id": iid, "scene": scene, "seed": seed}
        rows.append({"image": iid, "method": method, "spp": spp, "relmse": r, "psnr": p})
    return rows, list(images.values())


def test_per_seed_means_are_over_that_seeds_images_only() -> None:
    """Catches a mean over every image (no spread at all) or images given to the wrong seed."""
    rows, images = _doc({("a", 4, "x", 7): (1.0, 20.0), ("a", 4, "y", 7): (3.0, 30.0),
                         ("a", 4, "x", 8): (5.0, 22.0), ("a", 4, "y", 8): (7.0, 24.0)})
    (s,) = seed_spread(rows, images)
    assert (s["method"], s["spp"], s["seeds"], s["images_per_seed"]) == ("a", 4, [7, 8], 2)
    assert s["relmse"] == [2.0, 6.0] and s["psnr"] == [25.0, 23.0]


def test_no_spread_from_one_seed_or_from_different_scenes() -> None:
    """Catches a spread computed where it means nothing: one seed (no second rendering), or seeds
    holding other scenes (their means differ by scene, not by luck)."""
    rows, images = _doc({("a", 4, "x", 7): (1.0, 20.0), ("a", 4, "y", 7): (3.0, 30.0)})
    assert seed_spread(rows, images) == []
    rows, images = _doc({("a", 4, "x", 7): (1.0, 20.0), ("a", 4, "y", 8): (3.0, 30.0)})
    assert seed_spread(rows, images) == []
    rows, images = _doc({("a", 4, "x", 7): (1.0, 20.0), ("a", 4, "x", 8): (3.0, 30.0)})
    images.append({"id": "other", "scene": "x", "seed": None})  # an image that is not a seeded rendering
    assert seed_spread(rows, images) == []


def test_a_method_missing_a_seed_or_a_value_is_left_out() -> None:
    """Catches a per-seed mean over an empty list (NaN in the report) or over a None metric."""
    rows, images = _doc({("a", 4, "x", 7): (1.0, 20.0), ("a", 4, "x", 8): (3.0, 30.0),
                         ("b", 4, "x", 7): (1.0, 20.0), ("c", 4, "x", 7): (1.0, 20.0), ("c", 4, "x", 8): (None, 25.0)})
    assert [s["method"] for s in seed_spread(rows, images)] == ["a"]


def test_text_gives_the_standard_deviation_and_the_ratio_to_the_baseline() -> None:
    """Catches a population deviation where the sample one is meant (two seeds: sqrt 2 apart), or
    a ratio to the baseline taken across seeds instead of within each."""
    rows, images = _doc({("m", 4, "x", 7): (2.0, 20.0), ("m", 4, "x", 8): (4.0, 22.0),
                         ("oidn-high", 4, "x", 7): (1.0, 30.0), ("oidn-high", 4, "x", 8): (4.0, 30.0)})
    text = spread_text(seed_spread(rows, images))
    line = next(l for l in text.splitlines() if " m " in l)
    assert f"relMSE 3.0000 +- {np.std([2.0, 4.0], ddof=1):.4f} [2.0000-4.0000]" in line
    assert "PSNR 21.00 +- 1.41" in line
    assert "x oidn-high 1.00-2.00 (of the means: 1.20)" in line
    assert spread_text([]) == ""


def test_markdown_table_has_a_row_per_method_and_spp() -> None:
    """Catches the RESULTS.md block losing the spread (no table) or a row per seed instead of per method."""
    from mcdenoise.eval.seeds import spread_markdown

    rows, images = _doc({("m", 4, "x", 7): (2.0, 20.0), ("m", 4, "x", 8): (4.0, 22.0),
                         ("oidn-high", 4, "x", 7): (1.0, 30.0), ("oidn-high", 4, "x", 8): (4.0, 30.0)})
    md = spread_markdown(seed_spread(rows, images))
    table = [l for l in md if l.startswith("| 4 |")]
    assert len(table) == 2 and "| 1.00-2.00 | 1.20 |" in table[0] and table[1].endswith("- | - |")
    assert spread_markdown([]) == []


def test_results_block_has_a_per_scene_table_over_seeds() -> None:
    """Catches a many-seed RESULTS.md block without per-scene figures (the per-image tables stop at
    12 images) or with a per-scene value that is not the mean of that scene's renderings."""
    from mcdenoise.eval.resultsmd import _per_scene

    rows, images = _doc({("noisy", 4, "x", 7): (2.0, 20.0), ("noisy", 4, "x", 8): (4.0, 22.0),
                         ("noisy", 4, "y", 7): (1.0, 20.0), ("noisy", 4, "y", 8): (1.5, 22.0),
                         ("m", 4, "x", 7): (0.5, 30.0), ("m", 4, "x", 8): (1.5, 30.0),
                         ("m", 4, "y", 7): (0.2, 30.0), ("m", 4, "y", 8): (0.4, 30.0)})
    doc = {"rows": rows, "images": images, "methods": [{"name": "noisy"}, {"name": "m"}], "config": {"spp": [4]},
           "seed_spread": seed_spread(rows, images)}
    md = _per_scene(doc)
    assert "relMSE per scene at 4 spp, mean over the 2 render seeds (lowest in bold):" in md
    assert "| x | 3 | **1** |" in md and "| y | 1.25 | **0.3** |" in md
    assert _per_scene({**doc, "seed_spread": []}) == []
