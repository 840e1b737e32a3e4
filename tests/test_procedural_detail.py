"""The detailed procedural world (issue 19): fine surface detail on top of the rich world."""

from __future__ import annotations

import numpy as np
import pytest

from mcdenoise.render import procedural as P
from mcdenoise.render.procedural.detail import DETAIL_KINDS, detail_texture
from mcdenoise.render.procedural.rich import EXPOSURE_RANGE


@pytest.mark.parametrize("kind", sorted(DETAIL_KINDS))
def test_detail_textures_are_tileable_reflectances_with_fine_contrast(kind: str) -> None:
    """Catches a pattern that leaves [0, 1] (energy gain), shows a seam where the UV repeats, or is
    not fine at all (the point of the kind: contrast between neighbouring texels)."""
    for seed in range(3):
        rgb, h = detail_texture(np.random.default_rng(seed), kind, 128)
        assert rgb.shape == (128, 128, 3) and h.shape == (128, 128)
        assert rgb.dtype == np.float32 and np.float32(0.02) <= rgb.min() and rgb.max() <= np.float32(0.92)
        assert 0 <= h.min() and h.max() <= 1
        lum = rgb.mean(-1)
        # Seam: the wrap-around step is no larger than the steps inside the image.
        inner = np.abs(np.diff(lum, axis=1)).max()
        assert np.abs(lum[:, 0] - lum[:, -1]).max() <= inner + 1e-6
        inner_y = np.abs(np.diff(lum, axis=0)).max()
        assert np.abs(lum[0] - lum[-1]).max() <= inner_y + 1e-6
        # Fine: somewhere neighbouring texels differ by at least a fifth of the image's range.
        assert max(inner, inner_y) >= 0.2 * (lum.max() - lum.min()) > 0


def test_detail_textures_are_reproducible_and_kinds_are_checked() -> None:
    """Catches an unseeded draw (a recipe would not give the same dataset) and a typo drawing nothing."""
    for kind in DETAIL_KINDS:
        a = detail_texture(np.random.default_rng(4), kind, 64)
        b = detail_texture(np.random.default_rng(4), kind, 64)
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    with pytest.raises(ValueError, match="unknown detail texture"):
        detail_texture(np.random.default_rng(0), "plaid")


def test_detailed_world_keeps_the_rich_draw_and_adds_detail() -> None:
    """Catches the detail pass drawing from the rich stream (every rich dataset would change) or
    changing anything but materials; and a pass that never puts detail, varying roughness or bump on."""
    totals: dict[str, int] = {}
    for s in range(12):
        rich = P._draw(s, None, 32, 32, (10, 20), "rich")
        det = P._draw(s, None, 32, 32, (10, 20), "detailed")
        assert P.scene_digest(rich.scene) == P.scene_digest(P._draw(s, None, 32, 32, (10, 20), "rich").scene)
        assert sorted(rich.scene) == sorted(det.scene)  # same shapes, lights and sensor
        assert {k: v for k, v in det.info["rich"].items() if k != "detail"} == rich.info["rich"]
        for k in rich.scene:
            if isinstance(rich.scene[k], dict) and "bsdf" not in rich.scene[k]:
                assert P.scene_digest({"x": rich.scene[k]}) == P.scene_digest({"x": det.scene[k]}), k
        for k, n in det.info["rich"]["detail"].items():
            totals[k] = totals.get(k, 0) + n
        assert P.scene_digest(det.scene) == P.scene_digest(P._draw(s, None, 32, 32, (10, 20), "detailed").scene)
    assert sum(totals.get(k, 0) for k in DETAIL_KINDS) >= 12 * 3, totals
    assert totals.get("varying_roughness", 0) > 0 and totals.get("detail_bump", 0) > 0, totals
    assert EXPOSURE_RANGE["detailed"] == EXPOSURE_RANGE["rich"]


def test_the_dataset_command_offers_every_world() -> None:
    """Catches a world added to the generator but not to ``mcdenoise dataset --world`` (or the reverse)."""
    import argparse

    from mcdenoise.cli.dataset import add_parser
    from mcdenoise.render.procedural.rich import WORLDS

    p = argparse.ArgumentParser()
    add_parser(p)
    action = next(a for a in p._actions if "--world" in a.option_strings)
    assert tuple(action.choices) == WORLDS
