"""Procedural triangle meshes for the scene generator, built as numpy arrays.

Every builder returns ``(vertices (N, 3) float32, faces (M, 3) uint32, uvs (N, 2) float32)`` in
object space, centred near the origin with a radius of about 1, Y up, faces wound counter-clockwise
seen from outside (Mitsuba's BSDFs are one-sided, so the winding decides which side is lit).
:func:`to_mitsuba_mesh` turns the arrays into an ``mi.Mesh`` that a scene dict can hold directly.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

__all__ = [
    "MeshArrays",
    "grid_surface",
    "displaced_sphere",
    "torus",
    "extrusion",
    "superquadric",
    "twisted_column",
    "terrain",
    "signed_volume",
    "MESH_BUILDERS",
    "to_mitsuba_mesh",
    "mitsuba_module",
    "vertex_normals",
]

MeshArrays = tuple[np.ndarray, np.ndarray, np.ndarray]


def mitsuba_module() -> Any:
    """The configured ``mitsuba`` module (this process's variant, see ``_mitsuba``), imported on first use."""
    from mcdenoise.render._mitsuba import mitsuba

    return mitsuba()


def _value_noise_3d(p: np.ndarray, rng: np.random.Generator, octaves: int, freq: float) -> np.ndarray:
    """Smooth pseudo-random scalar field at points ``p`` (N, 3) -> (N,), roughly in [-1, 1].

    Sum of random plane waves (a cheap band-limited noise whose frequencies are drawn from ``rng``,
    so it is reproducible per seed and free of lattice artefacts).
    """
    out = np.zeros(len(p))
    amp = 1.0
    for o in range(octaves):
        waves = 4
        dirs = rng.normal(size=(waves, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        phase = rng.uniform(0, 2 * np.pi, size=waves)
        f = freq * (2.0**o)
        out += amp * np.sin(p @ dirs.T * f + phase).mean(axis=1)
        amp *= 0.5
    return out


def grid_surface(
    fn: Callable[[np.ndarray, np.ndarray], np.ndarray], nu: int, nv: int, *, wrap_u: bool, wrap_v: bool
) -> MeshArrays:
    """Triangulate a parametric surface ``fn(u, v) -> (nu', nv', 3)`` over [0, 1]^2.

    Wrapped directions reuse the first row instead of duplicating it, so the mesh is watertight
    there (UVs then jump at the seam, which only shifts the texture).
    """
    cu = nu if wrap_u else nu + 1
    cv = nv if wrap_v else nv + 1
    u = np.arange(cu) / nu
    v = np.arange(cv) / nv
    uu, vv = np.meshgrid(u, v, indexing="ij")
    pos = fn(uu, vv).reshape(-1, 3)
    uv = np.stack([uu, vv], -1).reshape(-1, 2)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    i1 = (i + 1) % cu
    j1 = (j + 1) % cv
    a, b, c, d = i * cv + j, i1 * cv + j, i1 * cv + j1, i * cv + j1
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return pos.astype(np.float32), faces.astype(np.uint32), uv.astype(np.float32)


def _sphere_param(uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
    # v runs pole to pole; u around the Y axis. Orientation chosen so that (du, dv) x is outward.
    theta = vv * np.pi
    phi = -uu * 2 * np.pi
    return np.stack([np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], -1)


def signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    """Signed volume enclosed by triangles ``f`` (M, 3) over ``v`` (N, 3): > 0 when wound outward."""
    v = v.astype(np.float64)
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def _outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Flip every face of a closed surface that is wound inward (one-sided BSDFs look black)."""
    return f[:, [0, 2, 1]] if signed_volume(v, f) < 0 else f


def _drop_degenerate(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    area = np.linalg.norm(np.cross(e1, e2), axis=1)
    return f[area > 1e-10]


def displaced_sphere(rng: np.random.Generator, res: int = 48) -> MeshArrays:
    """A unit sphere whose radius is modulated by smooth noise (blobs, rocks, potatoes)."""
    v, f, uv = grid_surface(_sphere_param, res, res // 2, wrap_u=True, wrap_v=False)
    amount = rng.uniform(0.05, 0.35)
    n = _value_noise_3d(v.astype(np.float64), rng, octaves=int(rng.integers(1, 4)), freq=rng.uniform(1.5, 5.0))
    v = v * (1.0 + amount * n)[:, None]
    f = _drop_degenerate(v, f)
    return v.astype(np.float32), _outward(v, f).astype(np.uint32), uv


def torus(rng: np.random.Generator, res: int = 48) -> MeshArrays:
    """A torus in the XZ plane with random tube radius, optionally squashed."""
    r_tube = rng.uniform(0.15, 0.45)
    r_major = 1.0 - r_tube
    squash = rng.uniform(0.5, 1.0)

    def fn(uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
        a = uu * 2 * np.pi
        b = vv * 2 * np.pi
        ring = r_major + r_tube * np.cos(b)
        return np.stack([ring * np.cos(a), squash * r_tube * np.sin(b), ring * np.sin(a)], -1)

    v, f, uv = grid_surface(fn, res, res // 2, wrap_u=True, wrap_v=True)
    return v, _outward(v, f).astype(np.uint32), uv


def _profile(rng: np.random.Generator) -> np.ndarray:
    """A random star-shaped closed 2D polygon (K, 2), counter-clockwise, radius <= 1."""
    k = int(rng.integers(3, 13))
    style = rng.integers(3)
    ang = np.sort(rng.uniform(0, 2 * np.pi, k)) if style == 0 else np.linspace(0, 2 * np.pi, k, endpoint=False)
    if style == 1:  # star: alternate radii
        k2 = 2 * k
        ang = np.linspace(0, 2 * np.pi, k2, endpoint=False)
        rad = np.where(np.arange(k2) % 2 == 0, 1.0, rng.uniform(0.3, 0.7))
    else:
        rad = rng.uniform(0.5, 1.0, len(ang))
    return np.stack([rad * np.cos(ang), rad * np.sin(ang)], -1)


def extrusion(rng: np.random.Generator, profile: np.ndarray | None = None) -> MeshArrays:
    """A star-shaped polygon extruded along Y, optionally tapered, capped at both ends."""
    prof = _profile(rng) if profile is None else profile
    k = len(prof)
    height = rng.uniform(0.4, 2.0)
    taper = rng.uniform(0.3, 1.0) if rng.random() < 0.5 else 1.0
    bottom = np.stack([prof[:, 0], np.full(k, -height / 2), prof[:, 1]], -1)
    top = np.stack([prof[:, 0] * taper, np.full(k, height / 2), prof[:, 1] * taper], -1)
    # Sides get their own vertices (sharp edges); caps are fans around a centre vertex.
    side_v = np.concatenate([bottom, top])
    idx = np.arange(k)
    nxt = (idx + 1) % k
    # Profile is CCW in (x, z); seen from outside, (b_i, t_i, b_{i+1}) winds outward.
    side_f = np.concatenate([np.stack([idx, k + idx, nxt], -1), np.stack([nxt, k + idx, k + nxt], -1)])
    c0 = len(side_v)
    cap_v = np.concatenate([bottom, [[0, -height / 2, 0]], top, [[0, height / 2, 0]]])
    b0, cb, t0, ct = c0, c0 + k, c0 + k + 1, c0 + 2 * k + 1
    bot_f = np.stack([np.full(k, cb), b0 + idx, b0 + nxt], -1)
    top_f = np.stack([np.full(k, ct), t0 + nxt, t0 + idx], -1)
    v = np.concatenate([side_v, cap_v])
    f = np.concatenate([side_f, bot_f, top_f])
    # UVs: around the profile x height on the sides, planar on the caps.
    seg = np.linalg.norm(prof - prof[np.roll(idx, 1)], axis=1)
    s = np.cumsum(seg) / seg.sum()
    side_uv = np.concatenate([np.stack([s, np.zeros(k)], -1), np.stack([s, np.ones(k)], -1)])
    cap_uv = cap_v[:, [0, 2]] * 0.5 + 0.5
    uv = np.concatenate([side_uv, cap_uv])
    # Winding fix-up: the profile is star-shaped about the origin, so "away from the origin" is
    # outward for every side and cap face whatever the profile's own orientation.
    f = _orient_outward(v, f)
    return v.astype(np.float32), f.astype(np.uint32), uv.astype(np.float32)


def _orient_outward(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Flip faces whose normal points towards the origin (valid for solids star-shaped about it)."""
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    n = np.cross(e1, e2)
    out = v[f].mean(axis=1)
    flip = (n * out).sum(axis=1) < 0
    f = f.copy()
    f[flip] = f[flip][:, [0, 2, 1]]
    return f


def superquadric(rng: np.random.Generator, res: int = 48) -> MeshArrays:
    """A superellipsoid: rounded cubes, cushions, diamonds, depending on two random exponents."""
    e1 = rng.uniform(0.2, 2.5)
    e2 = rng.uniform(0.2, 2.5)
    scale = rng.uniform(0.5, 1.0, 3)

    def spow(x: np.ndarray, e: float) -> np.ndarray:
        return np.sign(x) * np.abs(x) ** e

    def fn(uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
        theta = vv * np.pi - np.pi / 2
        phi = -uu * 2 * np.pi
        ct, st = spow(np.cos(theta), e1), spow(np.sin(theta), e1)
        return np.stack([ct * spow(np.cos(phi), e2) * scale[0], -st * scale[1], ct * spow(np.sin(phi), e2) * scale[2]], -1)

    v, f, uv = grid_surface(fn, res, res // 2, wrap_u=True, wrap_v=False)
    f = _orient_outward(v.astype(np.float64), _drop_degenerate(v, f))
    return v, f.astype(np.uint32), uv


def twisted_column(rng: np.random.Generator, res: int = 32) -> MeshArrays:
    """A polygonal column twisted about Y (sampled densely so the twist is smooth), capped."""
    prof = _profile(rng)
    k = len(prof)
    rows = res
    height = rng.uniform(1.0, 2.5)
    twist = rng.uniform(0.5, 3.0) * rng.choice([-1, 1])
    bulge = rng.uniform(0.0, 0.4)
    ys = np.linspace(-0.5, 0.5, rows + 1)
    ring = []
    for y in ys:
        a = twist * (y + 0.5)
        c, s = np.cos(a), np.sin(a)
        r = 1.0 + bulge * np.cos(np.pi * y * 2)
        x = (prof[:, 0] * c - prof[:, 1] * s) * r
        z = (prof[:, 0] * s + prof[:, 1] * c) * r
        ring.append(np.stack([x, np.full(k, y * height), z], -1))
    v = np.concatenate(ring)
    idx = np.arange(k)
    nxt = (idx + 1) % k
    faces = []
    for r in range(rows):
        b, t = r * k, (r + 1) * k
        faces.append(np.stack([b + idx, t + idx, b + nxt], -1))
        faces.append(np.stack([b + nxt, t + idx, t + nxt], -1))
    cb, ct = len(v), len(v) + 1
    v = np.concatenate([v, [[0, -height / 2, 0], [0, height / 2, 0]]])
    faces.append(np.stack([np.full(k, cb), idx, nxt], -1))
    top = rows * k
    faces.append(np.stack([np.full(k, ct), top + nxt, top + idx], -1))
    f = _orient_outward(v, np.concatenate(faces))
    uu = np.concatenate([np.tile(idx / k, rows + 1), [0.5, 0.5]])
    vv = np.concatenate([np.repeat(np.arange(rows + 1) / rows, k), [0.0, 1.0]])
    uv = np.stack([uu, vv], -1)
    return v.astype(np.float32), f.astype(np.uint32), uv.astype(np.float32)


def terrain(rng: np.random.Generator, size: float, res: int = 64, height: float = 1.0) -> MeshArrays:
    """A square height field of side ``size`` centred at the origin, facing +Y, flat near the centre
    (so objects placed at y=0 there rest on it) and rising into hills towards the edges."""

    def fn(uu: np.ndarray, vv: np.ndarray) -> np.ndarray:
        x = (uu - 0.5) * size
        z = (0.5 - vv) * size
        pts = np.stack([x, np.zeros_like(x), z], -1).reshape(-1, 3) / size
        h = _value_noise_3d(pts, np.random.default_rng(seed_h), octaves=3, freq=8.0).reshape(x.shape)
        rim = np.clip((np.maximum(np.abs(x), np.abs(z)) / (size / 2) - 0.25) / 0.75, 0, 1) ** 2
        return np.stack([x, height * (0.05 * h + rim * (1 + h)), z], -1)

    seed_h = int(rng.integers(2**31))
    return grid_surface(fn, res, res, wrap_u=False, wrap_v=False)


#: name -> builder(rng) for the random objects.
MESH_BUILDERS: dict[str, Callable[[np.random.Generator], MeshArrays]] = {
    "displaced_sphere": displaced_sphere,
    "torus": torus,
    "extrusion": extrusion,
    "superquadric": superquadric,
    "twisted_column": twisted_column,
}


def to_mitsuba_mesh(
    name: str, arrays: MeshArrays, *, bsdf: Any = None, to_world: np.ndarray | None = None, smooth: bool = True
) -> Any:
    """An ``mi.Mesh`` holding ``arrays`` (transformed by the 4x4 ``to_world``) with ``bsdf`` attached.

    ``bsdf`` is a Mitsuba BSDF object or plugin dict. Vertex normals are recomputed by Mitsuba
    (area-weighted) when ``smooth``; else faces are flat.
    """
    mi = mitsuba_module()
    v, f, uv = arrays
    if to_world is not None:
        v = (np.c_[v.astype(np.float64), np.ones(len(v))] @ np.asarray(to_world, np.float64).T)[:, :3]
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    mesh = mi.Mesh(name, len(v), len(f), props=props, has_vertex_normals=smooth, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(v, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(f, np.uint32).ravel())
    params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uv, np.float32).ravel())
    if smooth:
        # Our own normals, not mesh.recompute_vertex_normals(): that one accumulates with
        # parallel scatter-adds, whose order is not guaranteed; a fixed numpy order is
        # reproducible by construction (we did not measure Mitsuba's to differ).
        params["vertex_normals"] = mi.Float(vertex_normals(v, f).ravel())
    params.update()
    return mesh


def vertex_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3) float32, summed in a fixed order (deterministic)."""
    v = np.asarray(v, np.float64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # length = 2 * area
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    # Vertices of no face (dropped degenerate triangles) get any unit normal.
    n = np.where(length > 0, n / np.maximum(length, 1e-300), np.array([0.0, 1.0, 0.0]))
    return np.ascontiguousarray(n, np.float32)
