"""Draw, check and expose scenes: :func:`generate` and :func:`generate_scene`.

Rejected drawings are re-drawn from seeds derived from ``(seed, attempt)`` and freed at once (Dr.Jit
compiles calls to every live BSDF of the process).
"""

from __future__ import annotations

import gc
from typing import Any

import numpy as np

from mcdenoise.errors import SceneError
from mcdenoise.render.procedural import views as pv
from mcdenoise.render.procedural.draw import _draw
from mcdenoise.render.procedural.exposure import _scale_emitters
from mcdenoise.render.procedural.loading import load_procedural
from mcdenoise.render.procedural.objects import MAX_OBJECTS, MIN_OBJECTS
from mcdenoise.render.procedural.preview import preview_stats
from mcdenoise.render.procedural.rich import EXPOSURE_RANGE
from mcdenoise.render.procedural.scene import ProceduralScene
from mcdenoise.render.procedural.seeds import _loguniform, derive_seed

__all__ = ["MAX_ATTEMPTS", "generate", "generate_scene"]


MAX_ATTEMPTS = 12


def generate(
    seed: int,
    *,
    kind: str | None = None,
    width: int = 128,
    height: int = 128,
    check: bool = True,
    max_attempts: int = MAX_ATTEMPTS,
    objects: tuple[int, int] = (MIN_OBJECTS, MAX_OBJECTS),
    settings: Any = None,
    record_position: bool = False,
    keep_loaded: bool = False,
    world: str = "classic",
    stack: bool = False,
    small_emitters: float | None = None,
    strong_dof: float | None = None,
) -> ProceduralScene:
    """Draw a scene from ``seed``; with ``check``, re-draw rejected ones from derived seeds.

    ``world``: ``classic`` (the original generator) or ``rich`` (windows, small bright emitters,
    night, a wider exposure range: :mod:`~mcdenoise.render.procedural.rich`). ``small_emitters``:
    the probability that a rich scene keeps its small bright emitters (None: always).
    ``strong_dof``: the probability that a scene is shot through a wide lens (None: never).

    ``width``/``height`` set the film in the dict. ``objects`` is the (min, max) number of
    objects: indoor scenes count their furniture pieces in it when there is room. JIT compilation
    time grows with it: every object's material is compiled into the kernel separately. Raises
    SceneError when ``max_attempts`` drawings in a row are rejected.

    With ``keep_loaded`` the scene is loaded once at ``width`` x ``height`` (camera made opaque,
    :func:`~mcdenoise.render.procedural.views.set_camera`), checked on that very object with the
    render ``settings`` the caller will use (a RenderSettings, or a function of the drawn scene
    returning one, e.g. to include its motion) and ``record_position``, so the preview compiles
    the caller's kernel, and returned in :attr:`ProceduralScene.loaded` with its emitters
    rescaled in place. ``settings`` may also give ``(settings, block)``: the preview then measures
    its statistics on ``block`` x ``block`` pixel blocks (a check at fewer spp than the input).
    Without ``keep_loaded`` the preview is a small standalone render (``PREVIEW_SIZE``). With
    ``stack`` it renders as a view stack of the drawn camera (the kernel of stacked inputs).
    """
    reasons: list[str] = []
    for attempt in range(max_attempts):
        drawn = seed if attempt == 0 else derive_seed(seed, attempt)
        ps = _draw(drawn, kind, width, height, objects, world, small_emitters, strong_dof)
        ps.seed, ps.drawn_seed, ps.attempts = seed, drawn, attempt
        if keep_loaded:
            ps.loaded = load_procedural(ps, width, height)
            pv.set_camera(ps.loaded, ps.camera_to_world)
            # Emitter strengths opaque before the preview compiles (an envmap's scale loads as
            # a literal), so that the exposure fix below leaves the kernel as it is.
            pv.scale_loaded_emitters(ps.loaded, ps.scene)
        if not check:
            return ps
        pset = (settings(ps) if callable(settings) else settings) if keep_loaded else None
        pset, block = pset if isinstance(pset, tuple) else (pset, 1)
        stats = preview_stats(ps, scene=ps.loaded, settings=pset, block=block,
                              stack_camera=np.asarray(ps.camera_to_world) if stack and keep_loaded else None,
                              seed=derive_seed(drawn, 8) if keep_loaded else 0, record_position=record_position)
        problem = stats.problem()
        if problem is None:
            # Exposure: bring the median luminance into the world's EXPOSURE_RANGE (random in log space); the
            # median ignores the sun and lamps seen directly, which dominate the mean.
            target = _loguniform(np.random.default_rng(derive_seed(drawn, 7)), *EXPOSURE_RANGE[world])
            k = target / stats.median
            _scale_emitters(ps.scene, k)
            if ps.loaded is not None:
                pv.scale_loaded_emitters(ps.loaded, ps.scene, k)
            ps.info.update(
                preview={"mean": stats.mean * k, "median": target, "black_fraction": stats.black_fraction,
                         "object_fraction": stats.object_fraction},
                emitter_scale=k,
                rejected=reasons,
            )
            return ps
        reasons.append(f"seed {drawn}: {problem}")
        # Free the rejected scene now: Dr.Jit compiles calls to every live BSDF of the process.
        del ps
        gc.collect()
    raise SceneError(f"procedural scene seed {seed}: {max_attempts} drawings rejected ({'; '.join(reasons[-3:])})")


def generate_scene(seed: int, *, kind: str | None = None, objects: tuple[int, int] = (MIN_OBJECTS, MAX_OBJECTS)) -> dict:
    """Mitsuba scene dict of the checked scene drawn from ``seed`` (see :func:`generate`)."""
    return generate(seed, kind=kind, objects=objects).scene
