"""A load-independent emitter order for scenes whose emitter list Mitsuba shuffles.

Mitsuba 3.9 lists the emitters attached to *mesh* shapes (``rectangle``, ``cube``, ``obj``/``ply``
meshes) in an order that changes from one load of a scene to the next, ``parallel=False`` included
(``scripts/emitter_order_probe.py`` counts them). ``Scene.sample_emitter_direction``
picks the emitter by index in that list, so the same seed gave other pixels after every load: a
third-party scene's eval inputs (the kitchen's window and lamps) could not be rendered twice alike.

:func:`emitter_order` gives such a scene a canonical order (sorted by what the emitter is and
where, not by when it was loaded) and the sampling distribution over it; the integrator then picks
emitters through it (:func:`sample_emitter_direction`). Scenes without mesh emitters keep
Mitsuba's own path, so their pixels (every procedural dataset's) are unchanged.
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["emitter_order", "emitter_key", "sample_emitter_direction"]


def emitter_key(mi: Any, emitter: Any) -> tuple:
    """What an emitter is and where, independent of the load: class, bounding box, sampling weight,
    then its small parameters (radiance, intensity, scale, ...) and its shape's surface area."""
    bb = emitter.bbox()
    box = tuple(float(v) for v in (*bb.min, *bb.max)) if bb.valid() else ()
    params: list[tuple[str, tuple[float, ...]]] = []
    for name, value in sorted(mi.traverse(emitter).items()):
        shape = getattr(value, "shape", ())
        if int(np.prod(shape)) > 16:  # a texture or an environment map: its size alone, not a copy
            params.append((name, tuple(float(v) for v in shape)))
            continue
        try:
            arr = np.asarray(value, dtype=np.float64).ravel()
        except (TypeError, ValueError):
            continue
        params.append((name, tuple(arr.tolist())))
    surface = emitter.get_shape()
    area = float(np.asarray(surface.surface_area()).ravel()[0]) if surface is not None else -1.0
    return (emitter.class_name(), bool(emitter.is_environment()), box, float(emitter.sampling_weight()),
            tuple(params), area)


def emitter_order(mi: Any, scene: Any) -> tuple[Any, Any] | None:
    """``(perm, distribution)`` for a scene with two or more emitters of which at least one sits on
    a mesh: ``perm[j]`` is the scene index of the j-th emitter in canonical order (``mi.UInt32``),
    ``distribution`` a ``mi.DiscreteDistribution`` over that order by sampling weight. None where
    Mitsuba's own order is stable (no mesh emitter) or irrelevant (fewer than two emitters)."""
    emitters = list(scene.emitters())
    if len(emitters) < 2:
        return None
    if not any(e.get_shape() is not None and e.get_shape().is_mesh() for e in emitters):
        return None
    keys = [emitter_key(mi, e) for e in emitters]
    perm = sorted(range(len(emitters)), key=lambda i: keys[i])
    weights = [float(emitters[i].sampling_weight()) for i in perm]
    return mi.UInt32(perm), mi.DiscreteDistribution(mi.Float(weights))


def sample_emitter_direction(mi: Any, dr: Any, scene: Any, ref: Any, sample: Any, active: Any,
                             perm: Any, distr: Any) -> tuple[Any, Any]:
    """``Scene.sample_emitter_direction(ref, sample, True, active)`` with the emitter chosen in the
    canonical order of :func:`emitter_order`: the same estimator (pick by sampling weight, reuse
    the sample's first coordinate, emitter direction sample, shadow ray), another index map."""
    j, ux, pmf = distr.sample_reuse_pmf(sample.x, active)
    index = dr.gather(mi.UInt32, perm, j, active)
    emitter = dr.gather(mi.EmitterPtr, scene.emitters_dr(), index, active)
    ds, spec = emitter.sample_direction(ref, mi.Point2f(ux, sample.y), active)
    active = active & (ds.pdf != 0.0)
    ds.pdf *= pmf
    spec = spec * dr.select(pmf > 0.0, dr.rcp(pmf), 0.0)
    ray = ref.spawn_ray_to(ds.p)
    occluded = scene.ray_test(ray, active)
    spec = dr.select(active & ~occluded, spec, 0.0)
    return ds, spec
