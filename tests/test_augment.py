"""Flip/rotation augmentation: an augmented render equals a render of the transformed scene.

A tiny analytic ray caster (spheres and a plane, Mitsuba's thin-lens camera convention as in
mcdenoise.render.sequence: camera +X left, +Y up, +Z forward, film x right, y down) renders
per-sample normals, depth and positions for given sub-pixel and lens positions. For every one of
the 8 operations, augmenting that render must equal rendering the scene moved by the operation's
world map, with the augmented sub-pixel and lens positions; motion vectors must equal those
computed (by mcdenoise.render.sequence) for the moved scene and moved previous camera.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mcdenoise.data.format import pixel_stats
from mcdenoise.render.procedural import look_at
from mcdenoise.render.sequence import motion_vectors
from mcdenoise.train.augment import NUM_OPS, augment_arrays, film_matrix, spatial, world_matrix

N = 12  # square image (quarter turns of a pinhole image are exact only for square films)
FOV = 50.0
APERTURE, FOCUS = 0.08, 4.0


def _scene() -> tuple[list[tuple[np.ndarray, float]], tuple[np.ndarray, np.ndarray]]:
    spheres = [(np.array([0.3, 0.2, 0.5]), 0.6), (np.array([-0.8, -0.3, 1.2]), 0.5), (np.array([0.9, 0.7, -0.6]), 0.4)]
    plane = (np.array([0.0, 0.0, -1.5]), np.array([0.1, 0.2, 1.0]) / math.sqrt(1.05))  # backdrop: every ray hits
    return spheres, plane


def _move(scene, w: np.ndarray, origin: np.ndarray):
    spheres, (pp, pn) = scene
    mv = lambda p: origin + w @ (p - origin)  # noqa: E731
    return [(mv(c), r) for c, r in spheres], (mv(pp), w @ pn)


def _camera() -> np.ndarray:
    return look_at(np.array([0.4, 0.5, 5.0]), np.array([0.0, 0.1, 0.0]), np.array([0.1, 1.0, 0.0]))


def _trace(scene, cam: np.ndarray, sub: np.ndarray, lens: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample buffers ``(S, C, N, N)`` for sub-pixel ``sub`` and unit-disk ``lens`` ``(S, 2, N, N)``."""
    s = sub.shape[0]
    th = math.tan(math.radians(FOV) / 2)
    y, x = np.mgrid[0:N, 0:N]
    sx = (x[None] + sub[:, 0]) / N
    sy = (y[None] + sub[:, 1]) / N
    focus = np.stack([(1 - 2 * sx) * th, (1 - 2 * sy) * th, np.ones_like(sx)], -1) * FOCUS
    lo = np.stack([lens[:, 0] * APERTURE, lens[:, 1] * APERTURE, np.zeros_like(sx)], -1)
    d = focus - lo
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    r = cam[:3, :3]
    o = lo @ r.T + cam[:3, 3]
    d = d @ r.T
    spheres, (pp, pn) = scene
    best = np.full(o.shape[:-1], np.inf)
    normal = np.zeros_like(o)
    denom = d @ pn
    t = ((pp - o) @ pn) / np.where(np.abs(denom) > 1e-12, denom, 1e-12)
    ok = t > 1e-6
    best = np.where(ok, t, best)
    normal[ok] = pn
    for c, rad in spheres:
        oc = o - c
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - rad * rad)
        tt = -b - np.sqrt(np.maximum(disc, 0))
        hit = (disc > 0) & (tt > 1e-6) & (tt < best)
        best = np.where(hit, tt, best)
        normal[hit] = ((o + tt[..., None] * d - c) / rad)[hit]
    assert np.isfinite(best).all()
    pos = o + best[..., None] * d
    to = lambda a: np.ascontiguousarray(np.moveaxis(a, -1, 1)).astype(np.float64)  # noqa: E731
    return {"normal": to(normal), "position": to(pos), "depth": best[:, None], "subpixel": sub, "lens": lens}


def _samples(rng: np.random.Generator, s: int = 3) -> tuple[np.ndarray, np.ndarray]:
    sub = rng.random((s, 2, N, N))
    a = rng.random((s, N, N)) * 2 * np.pi
    rr = np.sqrt(rng.random((s, N, N)))
    return sub, np.stack([rr * np.cos(a), rr * np.sin(a)], 1)


@pytest.mark.parametrize("op", range(NUM_OPS))
def test_augmented_render_equals_render_of_transformed_scene(op: int) -> None:
    """Bug caught: a flip or turn that moves pixels but forgets to mirror sub-pixel or lens
    positions, reflects normals the wrong way, or turns vectors the wrong direction."""
    rng = np.random.default_rng(op)
    sub, lens = _samples(rng)
    cam = _camera()
    scene = _scene()
    render = _trace(scene, cam, sub, lens)
    w = world_matrix(op, cam)
    assert np.allclose(w @ w.T, np.eye(3)) and np.isclose(np.linalg.det(w), -1.0 if op >= 4 else 1.0)
    aug = augment_arrays(render, op, cam)
    moved = _trace(_move(scene, w, cam[:3, 3]), cam, aug["subpixel"], aug["lens"])
    for name in ("normal", "position", "depth"):
        np.testing.assert_allclose(aug[name], moved[name], atol=1e-9, err_msg=name)
    # Without the camera frame, world vectors stay: the moved scene in the moved world frame.
    plain = augment_arrays(render, op, None)
    np.testing.assert_allclose(plain["normal"], np.einsum("ij,sjhw->sihw", w.T, moved["normal"]), atol=1e-9)
    np.testing.assert_allclose(plain["subpixel"], aug["subpixel"])


@pytest.mark.parametrize("op", [1, 4, 6, 7])
def test_augmented_motion_equals_motion_of_transformed_scene(op: int) -> None:
    """Bug caught: motion vectors moved with the pixels but not turned/negated with them."""
    cam = _camera()
    prev = look_at(np.array([0.9, 0.2, 5.3]), np.array([0.1, 0.0, 0.0]), np.array([0.0, 1.0, 0.2]))
    scene = _scene()
    centre = np.full((1, 2, N, N), 0.5)
    zero = np.zeros((1, 2, N, N))

    def motion(sc, cur, prv):
        r = _trace(sc, cur, centre, zero)
        pos = np.moveaxis(r["position"][0], 0, -1)
        dirs = pos - cur[:3, 3]
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        return motion_vectors(pos, np.ones((N, N), bool), dirs, prv, FOV, N, N).astype(np.float64)

    mv = motion(scene, cam, prev)
    assert np.abs(mv).max() > 0.5  # the test means something only if things move
    w = world_matrix(op, cam)
    a = np.eye(3)
    a[:2, :2] = film_matrix(op)
    o = cam[:3, 3]
    prev_moved = np.eye(4)
    prev_moved[:3, :3] = w @ prev[:3, :3] @ np.linalg.inv(a)
    prev_moved[:3, 3] = o + w @ (prev[:3, 3] - o)
    want = motion(_move(scene, w, o), cam, prev_moved)
    np.testing.assert_allclose(augment_arrays({"motion": mv}, op, cam)["motion"], want, atol=1e-4)


def test_spatial_matches_film_matrix() -> None:
    """Bug caught: pixels moved one way and vectors turned the other (film_matrix out of step with
    numpy.rot90 / the flip)."""
    img = np.zeros((1, 5, 5))
    img[0, 1, 3] = 1.0  # film point (x, y) = (3.5, 1.5)
    for op in range(NUM_OPS):
        out = spatial(img, op)
        y, x = np.argwhere(out[0])[0]
        want = film_matrix(op) @ (np.array([3.5, 1.5]) - 2.5) + 2.5
        np.testing.assert_allclose([x + 0.5, y + 0.5], want)
    with pytest.raises(ValueError, match="square"):
        spatial(np.zeros((2, 3)), 1)
    assert augment_arrays({"radiance": img}, 0)["radiance"] is img


def test_statistics_commute_with_augmentation() -> None:
    """Bug caught: variance channels of 2-vectors not permuted with their means, so a pixel
    model's ``subpixel_variance``/``lens_variance`` disagree with its augmented samples."""
    rng = np.random.default_rng(3)
    sub, lens = _samples(rng, 5)
    cam = _camera()
    render = _trace(_scene(), cam, sub, lens)
    stats = {}
    for k, v in render.items():
        stats[k], stats[k + "_variance"] = pixel_stats(v)
    for op in range(NUM_OPS):
        aug = augment_arrays(render, op, cam)
        aug_stats = augment_arrays(stats, op, cam)
        for k in ("subpixel", "lens", "depth", "normal", "position"):
            m, v = pixel_stats(aug[k])
            np.testing.assert_allclose(aug_stats[k], m, atol=1e-5, err_msg=k)
            if k in ("normal", "position"):  # only the component mean is exact (no covariances stored)
                np.testing.assert_allclose(aug_stats[k + "_variance"].mean(0), v.mean(0), rtol=1e-4, atol=1e-8)
            else:
                np.testing.assert_allclose(aug_stats[k + "_variance"], v, rtol=1e-4, atol=1e-8, err_msg=k)


def test_loader_applies_one_op_to_input_and_target(tmp_path: Path) -> None:
    """Bug caught: input and target augmented with different ops (the model is asked to map a
    crop to a flipped target). Samples identical across the sample axis make the noisy target
    equal the input mean exactly, whatever op each row draws."""
    from mcdenoise.data.dataset import write_manifest
    from mcdenoise.data.format import ImageMeta, write_image
    from mcdenoise.models.registry import build_model
    from mcdenoise.train.data import DataConfig, batch_source

    from mcdenoise.data.channels import base_name, num_components

    rng = np.random.default_rng(0)
    model = build_model("kpcn", "small")
    chans = list(dict.fromkeys(["radiance", "diffuse", "specular", *(base_name(c) for c in model.required_channels())]))
    smp = {c: np.repeat(rng.random((1, num_components(c), 16, 16)).astype(np.float32), 4, 0) for c in chans}
    write_image(tmp_path / "a", meta=ImageMeta(16, 16, 4, chans, scene="a"), samples=smp, tile=8)
    write_manifest(tmp_path, [{"path": "a", "scene": "a", "split": "train"}])
    src = batch_source(tmp_path, model, DataConfig(crop=8, batch=8, workers=0, target="noisy"))
    b = src[0]
    np.testing.assert_array_equal(b["diffuse"].numpy(), b["target:diffuse"].numpy())
    # and the rows really were turned: not all equal to the unaugmented crops
    plain = batch_source(tmp_path, model, DataConfig(crop=8, batch=8, workers=0, target="noisy", augment=False))[0]
    assert not np.array_equal(plain["diffuse"].numpy(), b["diffuse"].numpy())
