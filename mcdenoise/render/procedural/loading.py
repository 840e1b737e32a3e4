"""Load a drawn scene's dict into Mitsuba, naming the seed when it fails."""

from __future__ import annotations

from typing import Any

from mcdenoise.errors import SceneError
from mcdenoise.render.procedural.scene import ProceduralScene

__all__ = ["load_procedural"]


def load_procedural(ps: ProceduralScene, width: int, height: int) -> Any:
    """Load ``ps.scene`` at ``width`` x ``height``; SceneError naming the seed when it fails."""
    from mcdenoise.render.api import load_scene

    try:
        return load_scene(ps.scene, width=width, height=height)
    except SceneError as e:
        raise SceneError(f"procedural scene (seed {ps.drawn_seed}) does not load: {e}") from None
