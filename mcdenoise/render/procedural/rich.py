"""The ``rich`` world: what real scenes have and the ``classic`` generator lacks (issue 19).

Added on top of a drawn classic layout, from a random stream of its own (so the classic draws
and their datasets stay bit-identical):

* window-lit rooms: one wall gets an opening with an emitting pane behind it (sky light), often
  slatted blinds in it and a narrow "sun" spot shining in; the ceiling lamps are switched off, so
  most of the room is lit indirectly and dim;
* small, very bright emitters (bulbs, LEDs, street lamps): spheres of a few millimetres to a few
  centimetres with radiance 1e2-1e5, seen directly and in glossy surfaces;
* night scenes outdoors: the sky dimmed by 1e-3-1e-1, so the small lamps dominate.

The exposure fix of :func:`~mcdenoise.render.procedural.generator.generate` then brings each
scene to a median drawn over two and a half orders of magnitude (``EXPOSURE_RANGE``), so the
networks see absolute brightness vary as much as it does between real renders.

Window panes are rectangles: the only mesh-like emitter of a scene (the classic world avoids
several, whose order Mitsuba 3.9 does not keep from load to load), so ceiling panels are removed
from window rooms.
"""

from __future__ import annotations

import numpy as np

from mcdenoise.render.procedural.objects import _Builder
from mcdenoise.render.procedural.seeds import _loguniform
from mcdenoise.render.procedural.transforms import _rotate, _scale, _translate, _xform, look_at

__all__ = ["WORLDS", "EXPOSURE_RANGE", "enrich"]

#: ``detailed`` is ``rich`` plus fine surface detail (:mod:`~mcdenoise.render.procedural.detail`).
WORLDS = ("classic", "rich", "detailed")

#: Median luminance range of the exposure fix, per world.
EXPOSURE_RANGE: dict[str, tuple[float, float]] = {"classic": (0.05, 0.5), "rich": (0.01, 2.0)}
EXPOSURE_RANGE["detailed"] = EXPOSURE_RANGE["rich"]  # the same scenes underneath

#: Walls as the classic indoor layout builds them: (centre as a function of the room, yaw).
_WALL_YAW = (0.0, np.pi, np.pi / 2, -np.pi / 2)


def _colour(rng: np.random.Generator) -> np.ndarray:
    """A light colour between warm (2700 K-ish) and cool white, in linear RGB, max 1."""
    warm = np.array([1.0, 0.72, 0.42])
    cool = np.array([0.8, 0.9, 1.0])
    t = rng.uniform()
    c = (1 - t) * warm + t * cool
    if rng.random() < 0.15:  # coloured LEDs
        c = rng.uniform(0.05, 1.0, 3)
    return c / c.max()


def _window_room(b: _Builder, rng: np.random.Generator) -> None:
    """Switch the lamps off and light the room through an opening in one wall."""
    assert b.room is not None
    hx, hz, h = b.room
    for lid in b.emitters:
        del b.scene[lid]
    b.emitters.clear()
    i = int(rng.integers(4))
    wall = b.scene.pop(f"wall_{i}")
    half = hx if i < 2 else hz
    centre = [np.array([0, h / 2, -hz]), np.array([0, h / 2, hz]), np.array([-hx, h / 2, 0]), np.array([hx, h / 2, 0])][i]
    rot = _rotate([0, 1, 0], _WALL_YAW[i])
    r3 = rot[:3, :3]
    wu = rng.uniform(0.3, min(1.6, half * 0.7))  # half width of the opening
    wv = rng.uniform(0.3, min(1.0, h * 0.35))  # half height
    u0 = rng.uniform(-half + wu + 0.1, half - wu - 0.1)
    v0 = rng.uniform(-h / 2 + wv + 0.2, h / 2 - wv - 0.05)

    def piece(name: str, ulo: float, uhi: float, vlo: float, vhi: float, bsdf: dict) -> None:
        if uhi - ulo < 1e-3 or vhi - vlo < 1e-3:
            return
        c = centre + r3 @ np.array([(ulo + uhi) / 2, (vlo + vhi) / 2, 0.0])
        m = _translate(c) @ rot @ _scale([(uhi - ulo) / 2, (vhi - vlo) / 2, 1.0])
        b.add(name, {"type": "rectangle", "id": name, "to_world": _xform(m), "bsdf": bsdf})

    mat = wall["bsdf"]
    piece(f"wall_{i}_left", -half, u0 - wu, -h / 2, h / 2, mat)
    piece(f"wall_{i}_right", u0 + wu, half, -h / 2, h / 2, mat)
    piece(f"wall_{i}_below", u0 - wu, u0 + wu, -h / 2, v0 - wv, mat)
    piece(f"wall_{i}_above", u0 - wu, u0 + wu, v0 + wv, h / 2, mat)
    # The pane: behind the opening (outside), facing into the room; sky-coloured.
    depth = rng.uniform(0.05, 0.6)
    sky = np.array([0.75, 0.85, 1.0]) * rng.uniform(0.8, 1.0) if rng.random() < 0.7 else _colour(rng)
    pane_c = centre + r3 @ np.array([u0, v0, -depth])
    m = _translate(pane_c) @ rot @ _scale([wu * 1.5 + depth, wv * 1.5 + depth, 1.0])
    radiance = sky * _loguniform(rng, 1.0, 20.0)
    b.add("window", {"type": "rectangle", "id": "window", "to_world": _xform(m),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance.tolist()}}})
    b.emitters.append("window")
    if rng.random() < 0.5:  # slatted blinds across the opening
        n = int(rng.integers(5, 16))
        thick = 2 * wv / n
        slat_mat = {"type": "diffuse", "reflectance": {"type": "rgb", "value": rng.uniform(0.3, 0.9, 3).tolist()}}
        tilt = _rotate([1, 0, 0], rng.uniform(-1.0, 1.0))
        for k in range(n):
            c = centre + r3 @ np.array([u0, v0 - wv + (k + 0.5) * thick, -0.02])
            sm = _translate(c) @ rot @ tilt @ _scale([wu, thick * 0.42, 0.004])
            b.add(f"blind_{k}", {"type": "cube", "id": f"blind_{k}", "to_world": _xform(sm), "bsdf": slat_mat})
    if rng.random() < 0.6:  # sunlight: a narrow spot outside, aimed through the opening at the floor
        inward = r3 @ np.array([0.0, 0.0, 1.0])
        tgt = centre + r3 @ np.array([u0 + rng.uniform(-wu, wu), v0, 0.0]) + inward * rng.uniform(0.5, 2.5)
        tgt[1] = 0.0
        through = centre + r3 @ np.array([u0, v0, 0.0])
        d = through - tgt
        src = through + d / np.linalg.norm(d) * rng.uniform(3.0, 8.0)
        b.add("sun", {"type": "spot", "id": "sun", "to_world": _xform(look_at(src, tgt, [0.1, 1.0, 0.2])),
                      "cutoff_angle": float(rng.uniform(6, 14)), "beam_width": float(rng.uniform(3, 5)),
                      "intensity": {"type": "rgb", "value": (np.array([1.0, 0.9, 0.75]) * _loguniform(rng, 100, 2000)).tolist()}})
        b.emitters.append("sun")
    if rng.random() < 0.5 and b.objects:  # one small lamp left on
        _small_emitters(b, rng, 1, indoor=True)


def _small_emitters(b: _Builder, rng: np.random.Generator, n: int, *, indoor: bool) -> None:
    """``n`` small, very bright spheres: near objects, on furniture, on walls or in the air."""
    start = sum(1 for e in b.emitters if e.startswith("bulb_"))
    centres = [c for c, _ in b.extents.values()]
    for j in range(start, start + n):
        r = _loguniform(rng, 0.003, 0.03) if indoor else _loguniform(rng, 0.01, 0.12)
        radiance = _colour(rng) * _loguniform(rng, 1e2, 1e5)
        if indoor and b.room is not None:
            hx, hz, h = b.room
            p = np.array([rng.uniform(-hx + 0.1, hx - 0.1), rng.uniform(0.1, h - 0.05), rng.uniform(-hz + 0.1, hz - 0.1)])
        else:
            p = np.array(centres[int(rng.integers(len(centres)))]) if centres else np.zeros(3)
            p = p + rng.normal(size=3) * 0.8
            p[1] = abs(p[1]) + r
        if centres and rng.random() < 0.6:  # beside an object, where glossy surfaces reflect it
            c = np.array(centres[int(rng.integers(len(centres)))])
            off = rng.normal(size=3)
            p = c + off / np.linalg.norm(off) * rng.uniform(0.3, 1.2) * (1.0 if indoor else 2.0)
            p[1] = max(p[1], r + 0.01)
        lid = f"bulb_{j}"
        b.add(lid, {"type": "sphere", "id": lid, "center": p.tolist(), "radius": float(r),
                    "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance.tolist()}}})
        b.emitters.append(lid)
        b.extents[lid] = (p.copy(), float(r))


def _dim_sky(b: _Builder, rng: np.random.Generator) -> None:
    """Night: the sky at 1e-3-1e-1 of its strength (scales load as literals: no kernel cost)."""
    sky = b.scene.get("sky")
    if not isinstance(sky, dict):
        return
    k = _loguniform(rng, 1e-3, 1e-1)
    if sky.get("type") == "envmap":
        sky["scale"] = float(sky.get("scale", 1.0) * k)
    elif sky.get("type") == "sunsky":
        sky["sun_scale"] = float(sky.get("sun_scale", 1.0) * k)
        sky["sky_scale"] = float(sky.get("sky_scale", 1.0) * k)


def enrich(b: _Builder, kind: str, rng: np.random.Generator, keep_small: bool = True) -> dict[str, object]:
    """Add the rich world's features to the drawn layout in ``b``; returns what was added (for meta.json).

    ``keep_small=False`` removes the small bright emitters once everything is drawn, so the scene is
    otherwise the one drawn with them (same room, window, night and stream); ``small_emitters_dropped``
    then says how many went (the key is absent otherwise, as in every draw made before the option)."""
    added: dict[str, object] = {"window": False, "small_emitters": 0, "night": False}
    if kind == "indoor":
        if rng.random() < 0.5:
            _window_room(b, rng)
            added["window"] = True
        if rng.random() < 0.6:
            n = int(rng.integers(1, 7))
            _small_emitters(b, rng, n, indoor=True)
    else:
        if rng.random() < 0.3:
            _dim_sky(b, rng)
            added["night"] = True
        if added["night"] or rng.random() < 0.5:
            n = int(rng.integers(1, 9))
            _small_emitters(b, rng, n, indoor=False)
    bulbs = [e for e in b.emitters if e.startswith("bulb_")]
    if not keep_small:
        for lid in bulbs:
            del b.scene[lid]
            b.extents.pop(lid, None)
        b.emitters[:] = [e for e in b.emitters if e not in bulbs]
        added["small_emitters_dropped"] = len(bulbs)
        bulbs = []
    added["small_emitters"] = len(bulbs)
    return added
