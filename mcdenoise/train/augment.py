"""Flips and 90-degree rotations of a crop that keep every channel consistent with its meaning.

The 8 operations are the symmetries of the square (dihedral group D4, :mod:`mcdenoise.data.symmetry`):
``op = k + 4 * flip`` first mirrors the crop left-right when ``flip``, then turns it ``k`` quarter
turns the way ``numpy.rot90(a, k, axes=(-2, -1))`` does. Each is the image of a rigid change of the world:

* A left-right mirror of the image is what the same camera sees of the scene reflected about the
  plane through the camera that holds its forward and up axes; a quarter turn is what it sees of
  the scene turned 90 degrees about its optical axis. (Exact for a pinhole or thin lens with
  square pixels and a square crop; the crop is square by construction.)

Channels follow from that (conventions of :mod:`mcdenoise.render.sequence`: film ``x`` right,
``y`` down, continuous pixel coordinates with pixel ``(x, y)`` covering ``[x, x+1) x [y, y+1)``;
Mitsuba's camera space has ``+X`` left and ``+Y`` up, i.e. both axes opposite to the film's, so a
2D film direction ``d`` and the camera-space vector ``-d`` transform by the same 2x2 matrix ``M``):

* scalars and colours (radiance, albedo, depth, roughness, time, lobes...): moved, not changed;
* ``subpixel`` (position in the pixel, [0, 1)^2): ``s' = M (s - 1/2) + 1/2`` (a mirror gives
  ``1 - x``); ``lens`` (camera-space disk point) and ``motion`` (film pixels): ``v' = M v``;
  variances of these 2-vectors swap components (``M`` is a signed permutation);
* world-space ``normal``, ``normal_diffuse`` and ``position``: with the camera frame in the image
  meta (``extra["camera_to_world"]``) they are transformed by the world map ``W = C A C^-1``
  (``C`` camera-to-world, ``A = diag(M, 1)`` in camera space; positions about the camera origin),
  exactly what rendering the transformed scene gives. Without a camera frame they are left as
  they are. That is still an exact rendering of the transformed scene, with its world coordinates
  expressed in the transformed world frame ``W`` (the scene and the frame move together); the
  models never see the camera frame, so a crop cannot tell the two apart, and the shape of every
  normal and position field (edges, discontinuities, variances) is preserved. What changes is
  only the prior over absolute directions (e.g. floors face +y), which the augmented crops
  spread over the 8 orientations either way.
* variances of world vectors under ``W``: ``Var((W n)_i) ~ sum_j W_ij^2 Var(n_j)`` (component
  covariances are not stored); their mean over components, the only form KPCN reads, is exact.

:func:`scale_exposure` is the other augmentation: one exposure factor for a whole crop, inputs and
targets alike, so a network sees each picture at many brightnesses (the same scene lit more or
less strongly renders exactly that, sample for sample).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mcdenoise.data.channels import base_name, exposure_power, is_variance_name
from mcdenoise.data.symmetry import FILM_VECTORS, NUM_OPS, film_matrix, spatial

__all__ = ["NUM_OPS", "film_matrix", "spatial", "world_matrix", "augment_arrays", "camera_frame", "scale_exposure",
           "draw_exposure"]

_WORLD_DIRECTIONS = frozenset({"normal", "normal_diffuse"})


def camera_frame(extra: Mapping[str, Any]) -> np.ndarray | None:
    """The ``4x4`` camera-to-world matrix an image meta records (``extra["camera_to_world"]``), or None."""
    c = extra.get("camera_to_world") if extra else None
    if c is None:
        return None
    c = np.asarray(c, np.float64)
    if c.shape != (4, 4) or not np.isfinite(c).all():
        return None
    return c


def world_matrix(op: int, camera_to_world: np.ndarray) -> np.ndarray:
    """``(3, 3)`` world map ``W = C A C^-1`` of op (``A = diag(M, 1)`` in camera space)."""
    a = np.eye(3)
    a[:2, :2] = film_matrix(op)
    c = np.asarray(camera_to_world, np.float64)[:3, :3]
    return c @ a @ np.linalg.inv(c)


def _vector(name: str, arr: np.ndarray, mat: np.ndarray, op: int, *, affine_center: np.ndarray | None = None) -> np.ndarray:
    """Apply ``mat`` to the component axis (-3) of ``(..., C, h, w)``, then move the pixels."""
    x = np.moveaxis(arr.astype(np.float64), -3, -1)
    if is_variance_name(name):
        y = x @ (mat * mat).T
    elif affine_center is not None:
        y = (x - affine_center) @ mat.T + affine_center
    else:
        y = x @ mat.T
    return spatial(np.moveaxis(y, -1, -3).astype(arr.dtype), op)


def augment_arrays(arrays: Mapping[str, np.ndarray], op: int, camera_to_world: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Apply op to every channel of a crop (see the module docstring).

    Args:
        arrays: name -> ``(C, h, w)`` or ``(S, C, h, w)`` (vocabulary names and ``*_variance``).
        op: 0..7; 0 is the identity (the arrays are returned as they are).
        camera_to_world: the image's ``4x4`` camera frame, or None.
    """
    if op == 0:
        return dict(arrays)
    m = film_matrix(op).astype(np.float64)
    w = None if camera_to_world is None else world_matrix(op, camera_to_world)
    out: dict[str, np.ndarray] = {}
    for name, arr in arrays.items():
        base = base_name(name)
        if base == "subpixel":
            centre = None if is_variance_name(name) else np.full(2, 0.5)
            out[name] = _vector(name, arr, m, op, affine_center=centre)
        elif base in FILM_VECTORS:
            out[name] = _vector(name, arr, m, op)
        elif w is not None and base in _WORLD_DIRECTIONS:
            out[name] = _vector(name, arr, w, op)
        elif w is not None and base == "position":
            origin = np.asarray(camera_to_world, np.float64)[:3, 3]
            out[name] = _vector(name, arr, w, op, affine_center=None if is_variance_name(name) else origin)
        else:
            out[name] = spatial(arr, op)
    return out


def scale_exposure(arrays: Mapping[str, np.ndarray], k: float) -> dict[str, np.ndarray]:
    """The crop at exposure ``k``: radiance-like channels times ``k``, their variances times ``k**2``
    (:func:`~mcdenoise.data.channels.exposure_power`), every other channel unchanged."""
    out: dict[str, np.ndarray] = {}
    for name, arr in arrays.items():
        p = exposure_power(name)
        out[name] = arr if p == 0 else (arr * np.float32(k) ** p).astype(arr.dtype, copy=False)
    return out


def draw_exposure(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    """An exposure factor log-uniform in ``bounds = (lo, hi)``, ``0 < lo <= hi``."""
    lo, hi = bounds
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
