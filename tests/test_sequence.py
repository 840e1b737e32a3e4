"""Camera paths, pinhole projection and motion vectors (mcdenoise.render.sequence)."""

from __future__ import annotations

import numpy as np
import pytest

from mcdenoise.render import sequence as sq
from mcdenoise.render.procedural import look_at


def test_project_inverts_pixel_rays() -> None:
    cam = look_at([1.0, 2.0, -3.0], [0.2, 0.5, 1.0], [0.1, 1.0, 0.0])
    o, d = sq.pixel_rays(cam, 50.0, 24, 16)
    xy, front = sq.project(o + 3.7 * d, cam, 50.0, 24, 16)
    assert front.all()
    y, x = np.mgrid[0:16, 0:24]
    np.testing.assert_allclose(xy[..., 0], x + 0.5, atol=1e-9)
    np.testing.assert_allclose(xy[..., 1], y + 0.5, atol=1e-9)
    # Directions at infinity project the same as far points.
    xy_inf, _ = sq.project(d, cam, 50.0, 24, 16, directions=np.ones((16, 24), bool))
    np.testing.assert_allclose(xy_inf, xy, atol=1e-9)


def test_project_behind_camera_is_nan() -> None:
    cam = look_at([0, 0, 0], [0, 0, 1], [0, 1, 0])
    xy, front = sq.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 2.0]]), cam, 60.0, 8, 8)
    assert front.tolist() == [False, True]
    assert np.isnan(xy[0]).all()
    np.testing.assert_allclose(xy[1], [4.0, 4.0])


@pytest.mark.render
def test_pixel_rays_match_mitsuba_sensor() -> None:
    """Our pinhole model is Mitsuba's perspective sensor (fov_axis x, non-square film)."""
    from mcdenoise.render._mitsuba import mitsuba

    mi = mitsuba()
    cam = look_at([0.5, 1.0, -2.0], [0.0, 0.3, 1.0], [0.2, 1.0, 0.0])
    w, h, fov = 12, 7, 55.0
    sensor = mi.load_dict({
        "type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(cam.tolist()),
        "film": {"type": "hdrfilm", "width": w, "height": h},
    })
    y, x = np.mgrid[0:h, 0:w]
    pos = mi.Point2f(((x.ravel() + 0.5) / w).astype(np.float32), ((y.ravel() + 0.5) / h).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    d_mi = np.stack([np.array(ray.d[i]) for i in range(3)], -1).reshape(h, w, 3)
    o, d = sq.pixel_rays(cam, fov, w, h)
    np.testing.assert_allclose(d, d_mi, atol=2e-6)
    np.testing.assert_allclose(o[0, 0], cam[:3, 3])


def test_motion_for_known_translation() -> None:
    """Camera slides sideways by dx in front of a wall at distance z: every pixel moves by
    dx / (z tan(fov/2)) * W/2 pixels, in the direction opposite to the camera's move."""
    w, h, fov, z, dx = 32, 24, 60.0, 5.0, 0.1
    prev = look_at([0, 0, 0], [0, 0, 1], [0, 1, 0])
    cur = look_at([dx, 0, 0], [dx, 0, 1], [0, 1, 0])  # +X world is the camera's left
    o, d = sq.pixel_rays(cur, fov, w, h)
    t = z / d[..., 2]
    pos = o + t[..., None] * d
    mv = sq.motion_vectors(pos, np.ones((h, w), bool), d, prev, fov, w, h)
    expect = dx / (z * np.tan(np.radians(fov) / 2)) * w / 2
    # Camera moved left, so the scene moves right on screen: positive x motion.
    np.testing.assert_allclose(mv[0], expect, rtol=1e-6)  # motion is stored as float32
    np.testing.assert_allclose(mv[1], 0.0, atol=1e-6)
    # Misses (directions at infinity) do not move under a pure translation.
    mv_inf = sq.motion_vectors(pos, np.zeros((h, w), bool), d, prev, fov, w, h)
    np.testing.assert_allclose(mv_inf, 0.0, atol=1e-6)


def test_motion_reprojects_to_previous_pixel() -> None:
    """For a rotation + translation, current pixel minus motion lands where the point was."""
    w, h, fov = 20, 20, 45.0
    prev = look_at([0, 1, -4], [0, 0, 0], [0, 1, 0])
    cur = look_at([0.3, 1.1, -3.8], [0.1, 0.05, 0], [0, 1, 0])
    o, d = sq.pixel_rays(cur, fov, w, h)
    pos = o + 4.0 * d
    mv = sq.motion_vectors(pos, np.ones((h, w), bool), d, prev, fov, w, h)
    prev_xy, _ = sq.project(pos, prev, fov, w, h)
    y, x = np.mgrid[0:h, 0:w]
    np.testing.assert_allclose(x + 0.5 - mv[0], prev_xy[..., 0], atol=1e-5)
    np.testing.assert_allclose(y + 0.5 - mv[1], prev_xy[..., 1], atol=1e-5)
    assert np.abs(mv).max() > 0.5  # the test case does move


def test_camera_path_smooth_and_starts_at_view() -> None:
    rng = np.random.default_rng(3)
    o, t, u = np.array([0.0, 1.0, -4.0]), np.zeros(3), np.array([0.0, 1.0, 0.0])
    path = sq.camera_path(o, t, u, 9, rng)
    assert len(path) == 9
    np.testing.assert_allclose(path[0], look_at(o, t, u), atol=1e-12)
    pos = np.array([m[:3, 3] for m in path])
    step = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert step.max() > 0
    # Smooth: no step is far larger than its neighbours, and all stay near the view.
    assert np.abs(np.diff(step)).max() < 0.5 * step.max() + 1e-9
    assert np.linalg.norm(pos - o, axis=1).max() <= 0.15 * 4.2 * np.sqrt(3) + 1e-9
    # Deterministic for a seed.
    again = sq.camera_path(o, t, u, 9, np.random.default_rng(3))
    np.testing.assert_array_equal(np.array(path), np.array(again))
