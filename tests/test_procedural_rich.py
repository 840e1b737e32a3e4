"""The rich procedural world (issue 19): windows, small bright emitters, night, wide exposure."""

from __future__ import annotations

import numpy as np
import pytest

from mcdenoise.errors import SceneError
from mcdenoise.render import procedural as P
from mcdenoise.render.procedural.rich import EXPOSURE_RANGE


def _draws(world: str, n: int = 40) -> list[P.ProceduralScene]:
    return [P._draw(s, None, 32, 32, (10, 20), world) for s in range(n)]


def test_classic_draws_do_not_depend_on_the_rich_code() -> None:
    """Catches the rich world drawing from the classic stream (every classic dataset would change)."""
    for s in range(10):
        a = P.scene_digest(P._draw(s, None, 32, 32, (10, 20)).scene)
        b = P.scene_digest(P._draw(s, None, 32, 32, (10, 20), "classic").scene)
        assert a == b


def test_rich_draws_are_reproducible() -> None:
    """Catches an unseeded draw in the rich features (a recipe would not give the same dataset)."""
    for s in range(5):
        assert P.scene_digest(P._draw(s, None, 32, 32, (10, 20), "rich").scene) == \
            P.scene_digest(P._draw(s, None, 32, 32, (10, 20), "rich").scene)


def test_rich_world_has_windows_small_bright_emitters_and_nights() -> None:
    """Catches a feature that is never drawn, or drawn wrong: window rooms keep no lamp panels (one
    mesh emitter at most, for reproducible emitter order), small emitters are small and 1e2-1e5 bright."""
    draws = _draws("rich")
    windows = [d for d in draws if d.info["rich"]["window"]]
    bulbs = [d for d in draws if d.info["rich"]["small_emitters"] > 0]
    nights = [d for d in draws if d.info["rich"]["night"]]
    assert windows and bulbs and nights
    for d in windows:
        rect_emitters = [k for k, v in d.scene.items() if isinstance(v, dict) and v.get("type") in ("rectangle", "cube", "disk")
                         and "emitter" in v]
        assert rect_emitters == ["window"], rect_emitters
        whole_walls = [k for k in d.scene if k in ("wall_0", "wall_1", "wall_2", "wall_3")]
        assert d.kind == "indoor" and len(whole_walls) == 3  # one wall was cut around the opening
    for d in bulbs:
        for k, v in d.scene.items():
            if k.startswith("bulb_"):
                assert v["radius"] <= 0.12 and 1e2 * 0.05 <= max(v["emitter"]["radiance"]["value"]) <= 1e5
    for d in nights:
        assert d.kind == "outdoor"


def test_unknown_world_is_refused() -> None:
    """Catches a typo silently drawing the classic world."""
    with pytest.raises(SceneError, match="world"):
        P._draw(0, None, 32, 32, (10, 20), "richer")
    assert EXPOSURE_RANGE["rich"][1] / EXPOSURE_RANGE["rich"][0] >= 100  # orders of magnitude between scenes


def test_small_emitter_rate_drops_only_the_small_emitters() -> None:
    """Catches a rate that changes the rest of the scene (room, window, night, materials: the data
    would differ in more than the one property the option names), one that leaves a bulb behind, one
    whose default (None) or rate 1 changes any draw (every rich and detailed dataset would change),
    and a rate that is not a probability per scene."""
    kept = dropped = 0
    for s in range(40):
        base = P._draw(s, None, 32, 32, (10, 20), "detailed")
        assert P.scene_digest(P._draw(s, None, 32, 32, (10, 20), "detailed", 1.0).scene) == P.scene_digest(base.scene)
        assert "small_emitters_dropped" not in base.info["rich"]
        none = P._draw(s, None, 32, 32, (10, 20), "detailed", 0.0)
        n = base.info["rich"]["small_emitters"]
        assert none.info["rich"]["small_emitters"] == 0 and none.info["rich"]["small_emitters_dropped"] == n
        assert not [k for k in none.scene if k.startswith("bulb_")]
        assert sorted(none.scene) == sorted(k for k in base.scene if not k.startswith("bulb_"))
        # The camera may refocus (a bulb can no longer be what it focuses on); everything else is as drawn.
        for k in none.scene:
            if k != "sensor":
                assert P.scene_digest({"x": none.scene[k]}) == P.scene_digest({"x": base.scene[k]}), (s, k)
        assert {k: v for k, v in none.info["rich"].items() if "small" not in k} == \
            {k: v for k, v in base.info["rich"].items() if "small" not in k}
        if n:
            half = P._draw(s, None, 32, 32, (10, 20), "detailed", 0.5)
            kept += half.info["rich"]["small_emitters"] == n
            dropped += half.info["rich"].get("small_emitters_dropped", 0) == n
    assert kept + dropped >= 20 and min(kept, dropped) >= 0.2 * (kept + dropped), (kept, dropped)


def test_wide_lens_changes_only_the_lens() -> None:
    """Catches a ``strong_dof`` rate that changes anything but the sensor (the data would differ in
    more than the one property the option names), a default (None) or rate 0 that changes any draw
    (every dataset made before the option would change), a wide lens weaker than the ordinary one
    (the option would add nothing), one that is not focused near the subject, and a rate that is
    not a probability per scene."""
    from mcdenoise.render.procedural.camera import WIDE_LENS_BLUR

    wide = 0
    for s in range(30):
        base = P._draw(s, None, 32, 32, (10, 20), "detailed")
        assert "wide_lens" not in base.info
        zero = P._draw(s, None, 32, 32, (10, 20), "detailed", None, 0.0)
        assert P.scene_digest(zero.scene) == P.scene_digest(base.scene) and zero.info["wide_lens"] is False
        one = P._draw(s, None, 32, 32, (10, 20), "detailed", None, 1.0)
        assert sorted(one.scene) == sorted(base.scene)
        for k in one.scene:
            if k != "sensor":
                assert P.scene_digest({"x": one.scene[k]}) == P.scene_digest({"x": base.scene[k]}), (s, k)
        sensor = one.scene["sensor"]
        assert sensor["type"] == "thinlens" and one.depth_of_field and one.info["wide_lens"] is True
        assert {k: v for k, v in sensor.items() if k not in ("type", "aperture_radius", "focus_distance")} == \
            {k: v for k, v in base.scene["sensor"].items() if k not in ("type", "aperture_radius", "focus_distance")}
        target = float(np.linalg.norm(one.camera_path[1] - one.camera_path[0]))
        assert 0.85 * target <= one.focus_distance <= 1.1 * target
        k = one.aperture_radius / (one.focus_distance * np.tan(np.radians(one.fov) / 2))
        assert WIDE_LENS_BLUR[0] * (1 - 1e-9) <= k <= WIDE_LENS_BLUR[1] * (1 + 1e-9)
        if base.depth_of_field:  # the ordinary lens blurs infinity by at most 0.08 of the half-width
            assert base.aperture_radius / (base.focus_distance * np.tan(np.radians(base.fov) / 2)) <= 0.08 + 1e-9
        wide += P._draw(s, None, 32, 32, (10, 20), "detailed", None, 0.5).info["wide_lens"]
    assert 6 <= wide <= 24, wide
